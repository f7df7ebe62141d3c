"""The never-worse job: the path whose volume predicts each stack best from the others wins."""

from __future__ import annotations

import numpy as np

from service.reconstruction import never_worse
from service.reconstruction.pipeline import ReconstructionConfig, ReconstructionResult
from service.io.volume import Volume
from service.reconstruction.slices import SliceSet


def fake_result(score: float | None) -> ReconstructionResult:
    quality = {"leave_one_stack_out": {"median_ncc": score}}
    return ReconstructionResult(None, np.eye(4)[None], np.ones(1), np.ones(1, bool), np.ones(1),  # type: ignore[arg-type]
                                {"total": 1.0}, quality=quality)


def tiny_slice_set() -> SliceSet:
    vol = Volume(np.ones((12, 12, 6), np.float32), np.diag([1.0, 1.0, 2.0, 1.0]))
    return SliceSet.from_stacks([(vol, None, np.repeat(vol.affine[None], 6, 0), np.ones(6, bool))])


def run_with(monkeypatch, scores: dict, job: ReconstructionConfig) -> tuple[ReconstructionResult, list]:  # noqa: ANN001
    """The job with every reconstruction faked: each path scores ``scores[path]``; further slice-level
    passes score ``scores["further"]`` in turn (None once they run out)."""
    calls = []
    further = list(scores.get("further", []))

    def fake(slice_set, resolution_mm, svr_iterations, progress, cancel, *, bounds_mm, config):  # noqa: ANN001, ANN202
        if not calls:
            name = "full"
        elif not config.register:
            name = "starting_poses"
        elif job.coarse_to_fine and "slice_level" not in calls:
            name = "slice_level"
        else:
            name = "further"
        calls.append(name)
        return fake_result(further.pop(0) if name == "further" and further else None if name == "further" else scores[name])

    monkeypatch.setattr(never_worse, "reconstruct", fake)
    return never_worse.reconstruct_never_worse(tiny_slice_set(), 1.0, 3, config=job), calls


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


def test_a_single_stack_keeps_the_full_job(monkeypatch) -> None:  # noqa: ANN001
    result, calls = run_with(monkeypatch, {"full": None, "starting_poses": 0.9, "slice_level": 0.9},
                             ReconstructionConfig())
    assert calls == ["full"] and result.quality["path"] == "full"
    assert result.quality["further_passes"] == {"scores": [], "kept": 0}


def test_further_slice_level_passes_are_kept_while_each_clearly_improves(monkeypatch) -> None:  # noqa: ANN001
    # From 0.81, 0.85 cuts the mismatch 1.27 x (kept); from 0.85, 0.86 only 1.07 x: it ends them.
    result, calls = run_with(monkeypatch, {"full": 0.62, "starting_poses": 0.47, "slice_level": 0.81,
                                           "further": [0.85, 0.86]}, ReconstructionConfig())
    assert calls == ["full", "starting_poses", "slice_level", "further", "further"]
    assert result.quality["further_passes"] == {"scores": [0.85, 0.86], "kept": 1}
    assert result.quality["leave_one_stack_out"]["median_ncc"] == 0.85 and result.quality["path"] == "slice_level"
    result, calls = run_with(monkeypatch, {"full": 0.62, "starting_poses": 0.47, "slice_level": 0.81,
                                           "further": [0.85, 0.9, 0.99]}, ReconstructionConfig())
    assert calls.count("further") == never_worse.MAX_FURTHER_PASSES == 2    # at most this many, all kept here
    assert result.quality["further_passes"] == {"scores": [0.85, 0.9], "kept": 2}
    assert result.quality["leave_one_stack_out"]["median_ncc"] == 0.9


def test_no_further_pass_where_the_starting_poses_win(monkeypatch) -> None:  # noqa: ANN001
    result, calls = run_with(monkeypatch, {"full": 0.935, "starting_poses": 0.93, "slice_level": 0.9,
                                           "further": [0.99]}, ReconstructionConfig())
    assert calls == ["full", "starting_poses", "slice_level"] and result.quality["path"] == "starting_poses"
    assert result.quality["further_passes"] == {"scores": [], "kept": 0}


def test_on_the_phantom_the_returned_poses_are_the_winning_paths(acquisition) -> None:  # noqa: ANN001
    ss = SliceSet.from_stacks([(v, m, t, np.ones(len(t), bool)) for (v, m), t in zip(acquisition.stacks, acquisition.truth)])
    res = never_worse.reconstruct_never_worse(ss, 1.5, 1, config=ReconstructionConfig(sr_iterations=3,
                                                                                      registration_iterations=5))
    q = res.quality
    assert q["path"] == never_worse.choose(q["paths"])
    if q["path"] == "starting_poses":
        assert np.allclose(res.atlas_from_voxel_final, ss.atlas_from_voxel)
