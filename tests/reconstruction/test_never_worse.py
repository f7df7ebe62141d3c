"""The never-worse job: the path whose volume predicts each stack best from the others wins."""

from __future__ import annotations

import numpy as np

from service.io.volume import Volume
from service.reconstruction import never_worse
from service.reconstruction.grid import make_grid
from service.reconstruction.config import ReconstructionConfig
from service.reconstruction.pipeline import ReconstructionResult
from service.reconstruction.slices import SliceSet


N_SLICES = 6


def fake_result(score: float | None, index: int, included: np.ndarray | None = None,
                coarse: object | None = None) -> ReconstructionResult:
    """A reconstruction's result scoring ``score``, every slice moved ``index`` mm along x (which call made it)."""
    poses = np.repeat(np.eye(4)[None], N_SLICES, 0)
    poses[:, 0, 3] = index
    inc = np.ones(N_SLICES, bool) if included is None else included
    return ReconstructionResult(None, poses, inc.astype(float), inc, np.ones(N_SLICES),  # type: ignore[arg-type]
                                {"total": 1.0}, make_grid(1.5, [[-30.0, -21, -3], [30, 21, 3]]),
                                [None if i else "residual_outlier" for i in inc], coarse,
                                {"leave_one_stack_out": {"median_ncc": score}})


def tiny_slice_set() -> SliceSet:
    vol = Volume(np.ones((12, 12, N_SLICES), np.float32), np.diag([1.0, 1.0, 2.0, 1.0]))
    return SliceSet.from_stacks([(vol, None, np.repeat(vol.affine[None], N_SLICES, 0), np.ones(N_SLICES, bool))])


def truth_slice_set(acquisition) -> SliceSet:  # noqa: ANN001
    """The phantom acquisition's slices at their true poses."""
    return SliceSet.from_stacks([(v, m, t, np.ones(len(t), bool))
                                 for (v, m), t in zip(acquisition.stacks, acquisition.truth)])


def run_with(monkeypatch, scores: dict, job: ReconstructionConfig, progress: list | None = None,  # noqa: ANN001
             made: dict | None = None, resolution_mm: float = 1.0, path_resolution_mm: float | None = None,
             log: list | None = None, bounds_mm: list | None = None) -> tuple[ReconstructionResult, list]:
    """The job with every reconstruction faked: each path scores ``scores[path]``; further slice-level
    passes score ``scores["further"]`` in turn (None once they run out); the passes at the output
    resolution (calls at ``resolution_mm`` below ``path_resolution_mm``) are given by ``made["output"]``.
    Returns the result and the calls: ``(name, x of the poses it started from, its coarse_to_fine)``.
    ``made``: per path, the result to return (``"further"`` and ``"output"``: a list, one a pass;
    default :func:`fake_result`); ``log`` collects each call's ``(name, resolution, bounds, register,
    coarse_to_fine)``."""
    calls = []
    further = list(scores.get("further", []))

    def fake(slice_set, resolution, svr_iterations, progress, cancel, *, bounds_mm, config):  # noqa: ANN001, ANN202
        names = [c[0] for c in calls]
        if calls and path_resolution_mm is not None and resolution < path_resolution_mm:
            name = "output"
        elif not calls:
            name = "full"
        elif not config.register:
            name = "starting_poses"
        elif job.coarse_to_fine and "slice_level" not in names:
            name = "slice_level"
        else:
            name = "further"
        assert slice_set.include.all() and len(slice_set.atlas_from_voxel) == N_SLICES
        calls.append((name, float(slice_set.atlas_from_voxel[0, 0, 3]), config.coarse_to_fine))
        if log is not None:
            log.append((name, resolution, bounds_mm, config.register, config.coarse_to_fine))
        if progress is not None:
            progress("registration 1/3", 0.5)
        if made and name in made:
            return made[name].pop(0) if name in ("further", "output") else made[name]
        score = (further.pop(0) if further else None) if name == "further" else scores[name]
        return fake_result(score, len(calls))

    monkeypatch.setattr(never_worse, "reconstruct", fake)
    report = None if progress is None else (lambda stage, f: progress.append((stage, f)))
    return never_worse.reconstruct_never_worse(tiny_slice_set(), resolution_mm, 3, report, config=job,
                                               path_resolution_mm=path_resolution_mm, bounds_mm=bounds_mm), \
        [c[0] for c in calls] if made is None and progress is None else calls


def test_a_diverged_full_job_gives_way(monkeypatch) -> None:  # noqa: ANN001
    result, calls = run_with(monkeypatch, {"full": 0.79, "starting_poses": 0.93, "slice_level": 0.95},
                             ReconstructionConfig())
    assert calls == ["full", "starting_poses", "slice_level", "further"]
    assert result.quality["path"] == "slice_level" and result.quality["paths"]["full"] == 0.79
    assert result.quality["further_passes"] == {"scores": [None], "kept": 0}
    assert result.quality["leave_one_stack_out"]["median_ncc"] == 0.95
    assert result.timings["all_paths"] == 4.0


def test_every_path_is_tried_and_the_best_registered_one_must_clearly_win(monkeypatch) -> None:  # noqa: ANN001
    result, calls = run_with(monkeypatch, {"full": 0.95, "starting_poses": 0.93, "slice_level": 0.0},
                             ReconstructionConfig())
    assert calls == ["full", "starting_poses", "slice_level", "further"] and result.quality["path"] == "full"
    result, calls = run_with(monkeypatch, {"full": 0.62, "starting_poses": 0.47, "slice_level": 0.81},
                             ReconstructionConfig())                      # the full job beat the start, the slices beat it
    assert calls == ["full", "starting_poses", "slice_level", "further"] and result.quality["path"] == "slice_level"
    result, calls = run_with(monkeypatch, {"full": 0.8, "starting_poses": 0.9, "slice_level": 0.85},
                             ReconstructionConfig(coarse_to_fine=False))
    assert calls == ["full", "starting_poses"] and result.quality["path"] == "starting_poses"
    result, calls = run_with(monkeypatch, {"full": 0.935, "starting_poses": 0.93, "slice_level": 0.9},
                             ReconstructionConfig())                      # better, but by too little
    assert calls == ["full", "starting_poses", "slice_level"] and result.quality["path"] == "starting_poses"


def test_the_gain_asked_for_grows_with_the_starting_mismatch() -> None:
    # 1.15 x less mismatch: from 0.95, 0.957 is enough and 0.955 is not; from 0.5, 0.55 is not and 0.61 is.
    assert never_worse.choose({"full": 0.957, "starting_poses": 0.95}) == "full"
    assert never_worse.choose({"full": 0.955, "starting_poses": 0.95}) == "starting_poses"
    assert never_worse.choose({"full": 0.55, "starting_poses": 0.5}) == "starting_poses"
    assert never_worse.choose({"full": 0.61, "starting_poses": 0.5, "slice_level": 0.58}) == "full"


def test_a_score_over_few_slices_must_win_by_more(monkeypatch) -> None:  # noqa: ANN001
    """The full path cuts the mismatch 1.17 x (0.796 -> 0.825): enough over 60 held-out slices or
    more, not over 28 (1.23 x asked); the job counts them on the starting poses' volume."""
    for slices, path in ((None, "full"), (60, "full"), (28, "starting_poses")):
        made = {name: fake_result(score, i) for i, (name, score) in
                enumerate((("full", 0.825), ("starting_poses", 0.796), ("slice_level", 0.8)))}
        for r in made.values():
            r.quality["leave_one_stack_out"]["slices"] = slices
        made["further"] = [fake_result(None, 9)]
        result, _ = run_with(monkeypatch, {}, ReconstructionConfig(), made=made)
        assert result.quality["path"] == path, slices
    assert never_worse.required_ratio(28) > 0.204 / 0.175 > never_worse.required_ratio(51) > never_worse.MIN_MISMATCH_RATIO


def test_a_single_stack_keeps_the_full_job(monkeypatch) -> None:  # noqa: ANN001
    result, calls = run_with(monkeypatch, {"full": None, "starting_poses": 0.9, "slice_level": 0.9},
                             ReconstructionConfig())
    assert calls == ["full"] and result.quality["path"] == "full"
    assert result.quality["further_passes"] == {"scores": [], "kept": 0}


def test_further_slice_level_passes_are_kept_while_each_clearly_improves(monkeypatch) -> None:  # noqa: ANN001
    monkeypatch.setattr(never_worse, "MAX_FURTHER_PASSES", 2)          # the loop, whatever the shipped count
    # From 0.81, 0.85 cuts the mismatch 1.27 x (kept); from 0.85, 0.86 only 1.07 x: it ends them.
    result, calls = run_with(monkeypatch, {"full": 0.62, "starting_poses": 0.47, "slice_level": 0.81,
                                           "further": [0.85, 0.86]}, ReconstructionConfig())
    assert calls == ["full", "starting_poses", "slice_level", "further", "further"]
    assert result.quality["further_passes"] == {"scores": [0.85, 0.86], "kept": 1}
    assert result.quality["leave_one_stack_out"]["median_ncc"] == 0.85 and result.quality["path"] == "slice_level"
    result, calls = run_with(monkeypatch, {"full": 0.62, "starting_poses": 0.47, "slice_level": 0.81,
                                           "further": [0.85, 0.9, 0.99]}, ReconstructionConfig())
    assert calls.count("further") == 2                                  # at most this many, all kept here
    assert result.quality["further_passes"] == {"scores": [0.85, 0.9], "kept": 2}
    assert result.quality["leave_one_stack_out"]["median_ncc"] == 0.9


def test_a_further_pass_starts_from_the_last_kept_poses_without_coarse_steps(monkeypatch) -> None:  # noqa: ANN001
    monkeypatch.setattr(never_worse, "MAX_FURTHER_PASSES", 2)
    progress: list = []
    result, calls = run_with(monkeypatch, {"full": 0.62, "starting_poses": 0.47, "slice_level": 0.81,
                                           "further": [0.85, 0.86]}, ReconstructionConfig(), progress)
    # calls 1-3 the paths (the slice level, call 3, wins); call 4 starts from its poses (x = 3),
    # call 5 from call 4's, which was kept (x = 4); neither has the coarse steps.
    assert calls[3:] == [("further", 3.0, False), ("further", 4.0, False)]
    assert result.atlas_from_voxel_final[0, 0, 3] == 4.0                  # the last kept pass is returned
    fractions = [f for _, f in progress]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    further = [f for stage, f in progress if stage == "further slice-level pass"]
    assert len(further) == 2 and all(0.85 <= f <= 1.0 for f in further)   # one report a pass, after the paths


def test_where_the_full_job_wins_without_a_slice_level_path_it_is_passed_on(monkeypatch) -> None:  # noqa: ANN001
    monkeypatch.setattr(never_worse, "MAX_FURTHER_PASSES", 2)
    progress: list = []
    result, calls = run_with(monkeypatch, {"full": 0.95, "starting_poses": 0.9, "further": [0.96, 0.962]},
                             ReconstructionConfig(coarse_to_fine=False), progress)
    assert [c[0] for c in calls] == ["full", "starting_poses", "further", "further"]
    assert calls[2][1] == 1.0 and result.quality["further_passes"] == {"scores": [0.96, 0.962], "kept": 1}
    fractions = [f for _, f in progress]
    assert fractions == sorted(fractions)


def test_a_kept_pass_keeps_the_winners_stack_outliers(monkeypatch) -> None:  # noqa: ANN001
    from types import SimpleNamespace

    inlier = np.array([True, True, False, True, True, True])
    coarse = SimpleNamespace(fit=SimpleNamespace(inlier=inlier))
    left_out = np.array([True, True, False, False, True, True])        # the pass leaves out slices 2 and 3
    made = {"full": fake_result(0.95, 1, coarse=coarse), "further": [fake_result(0.96, 4, left_out)]}
    monkeypatch.setattr(never_worse, "MAX_FURTHER_PASSES", 1)
    result, _ = run_with(monkeypatch, {"full": 0.95, "starting_poses": 0.9, "slice_level": 0.0},
                         ReconstructionConfig(), made=made)
    assert result.quality["further_passes"]["kept"] == 1 and result.coarse is coarse
    assert result.exclusion_reason == [None, None, "stack_outlier", "residual_outlier", None, None]


def test_no_further_pass_where_the_starting_poses_win(monkeypatch) -> None:  # noqa: ANN001
    result, calls = run_with(monkeypatch, {"full": 0.935, "starting_poses": 0.93, "slice_level": 0.9,
                                           "further": [0.99]}, ReconstructionConfig())
    assert calls == ["full", "starting_poses", "slice_level"] and result.quality["path"] == "starting_poses"
    assert result.quality["further_passes"] == {"scores": [], "kept": 0}


def test_paths_run_at_the_path_resolution_and_the_volume_at_the_output_one(monkeypatch) -> None:  # noqa: ANN001
    from types import SimpleNamespace

    inlier = np.array([True, True, False, True, True, True])
    coarse = SimpleNamespace(fit=SimpleNamespace(inlier=inlier))
    left_out = np.array([True, True, False, True, True, False])          # the output volume leaves out 2 and 5
    made = {"full": fake_result(0.62, 1, coarse=coarse), "output": [fake_result(0.68, 9, left_out)]}
    progress: list = []
    log: list = []
    result, calls = run_with(monkeypatch, {"full": 0.62, "starting_poses": 0.47, "slice_level": 0.0,
                                           "further": [0.7]}, ReconstructionConfig(), progress, made,
                             resolution_mm=0.8, path_resolution_mm=1.5, log=log)
    names = [c[0] for c in calls]
    assert names == ["full", "starting_poses", "slice_level", "further", "output"]
    assert [r for _, r, *_ in log] == [1.5] * 4 + [0.8]
    # a registered path won: the output pass is the slice level (registration, no coarse steps) from
    # the kept further pass's poses (call 4: x = 4); its field of view is the pixels' box there (12 x
    # 12 pixels of 1 mm from x = 4, a 5 mm margin) within the field of view that pass had (z: +-3 mm)
    assert calls[-1][1] == 4.0 and log[-1][3:] == (True, False)
    assert np.allclose(log[-1][2], [[-1.0, -5, -3], [20, 16, 3]])
    q = result.quality
    assert q["path"] == "full" and q["paths"]["full"] == 0.62 and q["path_resolution_mm"] == 1.5
    assert q["further_passes"] == {"scores": [0.7], "kept": 1}
    assert q["output_pass"] == {"tried": True, "score": 0.68, "kept": True}   # a little worse than 0.7: kept
    assert q["leave_one_stack_out"]["median_ncc"] == 0.68                   # measured on the volume returned
    assert result.coarse is coarse
    assert result.exclusion_reason == [None, None, "stack_outlier", None, None, "residual_outlier"]
    fractions = [f for _, f in progress]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    share = never_worse.OUTPUT_SHARE
    output = [f for stage, f in progress if stage == "volume at the output resolution"]
    assert output == [share + (1 - share) * 0.8 * 0.5]


def test_an_output_pass_gives_way_where_the_chosen_poses_do_clearly_better_at_its_resolution(
        monkeypatch) -> None:  # noqa: ANN001
    from types import SimpleNamespace

    coarse = SimpleNamespace(fit=SimpleNamespace(inlier=np.array([True, False, True, True, True, True])))
    left_out = np.array([True, False, True, True, True, True])
    made = {"full": fake_result(0.7, 1, coarse=coarse),
            "output": [fake_result(0.6, 9), fake_result(0.75, 10, left_out)]}
    log: list = []
    progress: list = []
    result, calls = run_with(monkeypatch, {"full": 0.7, "starting_poses": 0.47, "slice_level": 0.0},
                             ReconstructionConfig(), progress, made, resolution_mm=0.8, path_resolution_mm=1.5,
                             log=log)
    fractions = [f for _, f in progress]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert result.coarse is coarse and result.exclusion_reason[1] == "stack_outlier"   # no further pass kept
    assert [c[0] for c in calls] == ["full", "starting_poses", "slice_level", "further", "output", "output"]
    assert [entry[3] for entry in log[-2:]] == [True, False] and calls[-1][1] == 1.0   # at the full job's poses
    assert result.quality["output_pass"] == {"tried": True, "score": 0.6, "kept": False, "against": 0.75}
    assert result.quality["leave_one_stack_out"]["median_ncc"] == 0.75
    assert result.timings["all_paths"] == 6.0
    # judged at the output resolution, the pass is not clearly worse than the chosen poses' volume there
    made = {"output": [fake_result(0.6, 9), fake_result(0.61, 10)]}
    result, _ = run_with(monkeypatch, {"full": 0.7, "starting_poses": 0.47, "slice_level": 0.0},
                         ReconstructionConfig(), made=made, resolution_mm=0.8, path_resolution_mm=1.5)
    assert result.quality["output_pass"] == {"tried": True, "score": 0.6, "kept": True, "against": 0.61}
    assert result.quality["leave_one_stack_out"]["median_ncc"] == 0.6


def test_where_the_starting_poses_win_the_output_volume_registers_nothing(monkeypatch) -> None:  # noqa: ANN001
    log: list = []
    result, calls = run_with(monkeypatch, {"full": 0.9, "starting_poses": 0.93, "slice_level": 0.9},
                             ReconstructionConfig(), made={"output": [fake_result(0.94, 9)]}, resolution_mm=0.8,
                             path_resolution_mm=1.5, log=log)
    assert [c[0] for c in calls] == ["full", "starting_poses", "slice_level", "output"]
    assert log[-1][1] == 0.8 and log[-1][3] is False and calls[-1][1] == 2.0       # the starting-poses path's
    assert result.quality["output_pass"] == {"tried": False, "score": None, "kept": False}


def test_an_undecided_choice_is_made_again_at_the_output_resolution(monkeypatch) -> None:  # noqa: ANN001
    # At the paths' resolution the full job cuts the starting poses' mismatch 0.07 -> 0.065 (1.08 x:
    # not enough to win, enough to ask again); at the output resolution its slice level, from its
    # poses, against the starting poses' volume.
    scores = {"full": 0.935, "starting_poses": 0.93, "slice_level": 0.9}
    for fine, path in ((0.95, "full"), (0.935, "starting_poses")):
        log: list = []
        made = {"output": [fake_result(0.93, 9), fake_result(fine, 10)]}
        progress: list = []
        result, calls = run_with(monkeypatch, scores, ReconstructionConfig(), progress, made, resolution_mm=0.8,
                                 path_resolution_mm=1.5, log=log)
        fractions = [f for _, f in progress]
        assert fractions == sorted(fractions) and result.timings["all_paths"] == 5.0
        assert [c[0] for c in calls] == ["full", "starting_poses", "slice_level", "output", "output"]
        assert (calls[-2][1], log[-2][3]) == (2.0, False)                  # the starting poses' volume
        assert (calls[-1][1], *log[-1][3:]) == (1.0, True, False)           # the full job's poses, slice level
        q = result.quality
        assert q["path"] == path and q["output_pass"] == {"tried": True, "score": fine, "kept": path == "full",
                                                          "against": 0.93}
        assert q["leave_one_stack_out"]["median_ncc"] == (fine if path == "full" else 0.93)
    log = []
    run_with(monkeypatch, {"full": 0.934, "starting_poses": 0.93, "slice_level": 0.9}, ReconstructionConfig(),
             made={"output": [fake_result(0.93, 9)]}, resolution_mm=0.8, path_resolution_mm=1.5, log=log)
    assert [e[0] for e in log] == ["full", "starting_poses", "slice_level", "output"]     # 1.06 x: decided


def test_one_resolution_without_registration_or_for_a_coarse_volume(monkeypatch) -> None:  # noqa: ANN001
    log: list = []
    run_with(monkeypatch, {"full": 0.9}, ReconstructionConfig(register=False), resolution_mm=0.8,
             path_resolution_mm=1.5, log=log)
    assert [(n, r) for n, r, *_ in log] == [("full", 0.8)]
    log.clear()
    result, _ = run_with(monkeypatch, {"full": 0.95, "starting_poses": 0.9, "slice_level": 0.0},
                         ReconstructionConfig(), resolution_mm=2.0, path_resolution_mm=1.5, log=log)
    assert [n for n, *_ in log] == ["full", "starting_poses", "slice_level", "further"]
    assert {r for _, r, *_ in log} == {2.0} and result.quality["path_resolution_mm"] == 2.0
    assert "output_pass" not in result.quality


def test_on_the_phantom_the_result_is_the_winner_or_its_last_kept_pass(acquisition) -> None:  # noqa: ANN001
    ss = truth_slice_set(acquisition)
    res = never_worse.reconstruct_never_worse(ss, 1.5, 1, config=ReconstructionConfig(sr_iterations=3,
                                                                                      registration_iterations=5))
    q = res.quality
    assert q["path"] == never_worse.choose(q["paths"])
    further = q["further_passes"]
    assert further["kept"] <= len(further["scores"]) <= never_worse.MAX_FURTHER_PASSES
    returned = further["scores"][further["kept"] - 1] if further["kept"] else q["paths"][q["path"]]
    assert q["leave_one_stack_out"]["median_ncc"] == returned
    if q["path"] == "starting_poses":
        assert np.allclose(res.atlas_from_voxel_final, ss.atlas_from_voxel) and not further["scores"]


def test_on_the_phantom_a_finer_volume_is_solved_from_the_coarse_paths(acquisition) -> None:  # noqa: ANN001
    ss = truth_slice_set(acquisition)
    res = never_worse.reconstruct_never_worse(ss, 1.5, 1, config=ReconstructionConfig(sr_iterations=3,
                                                                                      registration_iterations=5),
                                              path_resolution_mm=2.5)
    q = res.quality
    assert np.allclose(res.volume.spacing, 1.5) and q["path_resolution_mm"] == 2.5
    assert q["path"] in never_worse.PATHS and set(q["output_pass"]) >= {"tried", "score", "kept"}
    if q["output_pass"]["kept"]:                          # the volume returned is the pass's own
        assert q["leave_one_stack_out"]["median_ncc"] == q["output_pass"]["score"]


def test_an_output_volume_whose_slices_lie_beyond_the_paths_grid_keeps_that_grid(monkeypatch) -> None:  # noqa: ANN001
    log: list = []
    made = {"full": fake_result(0.62, 100), "output": [fake_result(0.7, 9)]}      # every pixel at x >= 100 mm
    run_with(monkeypatch, {"full": 0.62, "starting_poses": 0.47, "slice_level": 0.0}, ReconstructionConfig(),
             made=made, resolution_mm=0.8, path_resolution_mm=1.5, log=log)
    assert log[-1][0] == "output" and np.allclose(log[-1][2], [[-30.0, -21, -3], [30, 21, 3]])


def test_a_field_of_view_given_is_the_output_volumes_too(monkeypatch) -> None:  # noqa: ANN001
    log: list = []
    bounds = [[-10.0, -10, -10], [10, 10, 10]]
    run_with(monkeypatch, {"full": 0.9, "starting_poses": 0.93, "slice_level": 0.9}, ReconstructionConfig(),
             made={"output": [fake_result(0.94, 9)]}, resolution_mm=0.8, path_resolution_mm=1.5, log=log,
             bounds_mm=bounds)
    assert [e[2] for e in log] == [bounds] * 4


def test_no_registered_path_whose_stacks_do_not_predict_each_other_replaces_the_starting_poses(monkeypatch) -> None:  # noqa: ANN001
    """A stack whose contrast defeats the NCC: every path scores under 0.5, the full job 2.3 x better
    than the start. Nothing shows the registration did better, at the paths' resolution or the output's."""
    log: list = []
    made = {"output": [fake_result(0.15, 9)]}
    result, calls = run_with(monkeypatch, {"full": 0.41, "starting_poses": 0.18, "slice_level": 0.21},
                             ReconstructionConfig(), made=made, resolution_mm=0.8, path_resolution_mm=1.5, log=log)
    assert [c[0] for c in calls] == ["full", "starting_poses", "slice_level", "output"]
    assert result.quality["path"] == "starting_poses" and log[-1][3] is False     # solved at the poses given
    result, _ = run_with(monkeypatch, {"full": 0.62, "starting_poses": 0.18, "slice_level": 0.21},
                         ReconstructionConfig())                                  # a coherent path still wins
    assert result.quality["path"] == "full"


def test_no_registration_round_gives_the_robust_volume_of_the_starting_poses(acquisition) -> None:  # noqa: ANN001
    """``svr_iterations=0`` (the API's "no registration rounds"): the slices stay where they were given
    and the volume is the robust super-resolved one, nearer the truth than their Gaussian average,
    and the report names the path ``starting_poses``: no slice moved."""
    from service.reconstruction.pipeline import reconstruct
    from tests.reconstruction.helpers import psnr_ncc, reference_on

    ss = truth_slice_set(acquisition)
    cfg = ReconstructionConfig(sr_iterations=3)
    res = never_worse.reconstruct_never_worse(ss, 1.5, 0, config=cfg)
    average = reconstruct(ss, 1.5, 0, config=cfg)
    assert res.quality["path"] == "starting_poses" and set(res.quality["paths"]) == {"starting_poses"}
    assert np.allclose(res.atlas_from_voxel_final, ss.atlas_from_voxel) and res.timings["superresolution"] > 0
    robust, plain = (psnr_ncc(r.volume.array, *reference_on(r.grid, acquisition))[0] for r in (res, average))
    assert robust > plain + 3.0, (robust, plain)                       # dB; 38 against 28 on this phantom
