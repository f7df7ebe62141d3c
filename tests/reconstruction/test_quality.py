"""The quality report without ground truth: high where the poses are true, and the leave-one-stack-out
score singles out a stack placed where it was not acquired."""

from __future__ import annotations

import numpy as np

from service.geometry.pose import translate
from service.reconstruction.config import ReconstructionConfig
from service.reconstruction.pipeline import reconstruct
from service.reconstruction.quality import MIN_ALTERNATE_NCC, quality_report
from service.reconstruction.slices import SliceSet
from tests.reconstruction.helpers import perturb

FAST = ReconstructionConfig(register=False, sr_iterations=4)


def test_true_poses_score_high_and_a_misplaced_stack_scores_low_when_left_out(acquisition) -> None:  # noqa: ANN001
    truth = [(vol, mask, t, np.ones(len(t), bool)) for (vol, mask), t in zip(acquisition.stacks, acquisition.truth)]
    good = reconstruct(SliceSet.from_stacks(truth), resolution_mm=1.5, svr_iterations=1, config=FAST)
    q = good.quality
    assert q["judged_slices"] > 0.8 * len(good.ncc)
    assert q["median_ncc"] > 0.9 and q["fraction_ncc_above_0_7"] > 0.9
    assert min(q["leave_one_stack_out"]["per_stack_median_ncc"]) > 0.8
    assert np.all(np.isfinite(good.held_out_ncc[good.included]))

    wrong = list(truth)
    vol, mask, t, use = wrong[1]
    wrong[1] = (vol, mask, translate([6.0, -5.0, 4.0]) @ t, use)            # placed 9 mm from where it was
    bad = reconstruct(SliceSet.from_stacks(wrong), resolution_mm=1.5, svr_iterations=1, config=FAST)
    held = bad.quality["leave_one_stack_out"]["per_stack_median_ncc"]
    assert held[1] < min(held[0], held[2]) - 0.1, held
    assert bad.quality["leave_one_stack_out"]["median_ncc"] < q["leave_one_stack_out"]["median_ncc"]
    assert q["coherent"] is True


def test_the_slices_are_judged_against_the_volume_returned(acquisition, monkeypatch) -> None:  # noqa: ANN001
    """The per-slice NCCs (and so the report) are those of the volume the job returns, after its
    compact-body step: a spike that step takes off the volume no longer lets a slice agree with it.
    Here the step also darkens the volume along x, so the two volumes give the slices NCCs far apart."""
    from service.reconstruction import pipeline
    from service.reconstruction.forward import ForwardModel
    from service.reconstruction.quality import slice_ncc

    kept = {}
    real = pipeline.compact_brain

    def compact_and_darken(x, spacing):  # noqa: ANN001, ANN202 - a compact step that visibly changes the volume
        kept["before"] = x.copy()
        kept["returned"] = out = real(x, spacing) * np.linspace(0.2, 1.0, x.shape[0])[:, None, None]
        return out

    monkeypatch.setattr(pipeline, "compact_brain", compact_and_darken)
    placed = [(vol, mask, t, np.ones(len(t), bool)) for (vol, mask), t in zip(acquisition.stacks, acquisition.truth)]
    ss = SliceSet.from_stacks(placed)
    res = reconstruct(ss, resolution_mm=2.0, svr_iterations=0, config=FAST)
    np.testing.assert_array_equal(res.volume.array, kept["returned"].astype(np.float32))
    model = ForwardModel(ss, res.atlas_from_voxel_final, res.grid, psf_points=FAST.psf_points)   # unbinned
    off = {k: np.nanmax(np.abs(res.ncc - slice_ncc(model.forward(v), ss.values, ss.slice_id, ss.n_slices)))
           for k, v in kept.items()}
    assert off["returned"] < 0.1 < 0.5 < off["before"], off


def test_quality_can_be_off(acquisition) -> None:  # noqa: ANN001
    vol, mask = acquisition.stacks[0]
    ss = SliceSet.from_stacks([(vol, mask, acquisition.truth[0], np.ones(len(acquisition.truth[0]), bool))])
    res = reconstruct(ss, resolution_mm=2.0, svr_iterations=0, config=ReconstructionConfig(quality=False))
    assert res.quality is None and res.held_out_ncc is None
    single = reconstruct(ss, resolution_mm=2.0, svr_iterations=0)
    assert single.quality["leave_one_stack_out"]["median_ncc"] is None        # one stack: no other to leave out


def test_one_stack_is_judged_by_its_alternate_slices_and_scrambled_poses_are_told_apart(acquisition) -> None:  # noqa: ANN001
    """A lone stack's slices agree with a volume made of themselves wherever they are put; its even
    slices left out are predicted by its odd ones only where the slices sit where they were acquired."""
    vol, mask = acquisition.stacks[0]
    truth = acquisition.truth[0]
    use = np.ones(len(truth), bool)
    good = reconstruct(SliceSet.from_stacks([(vol, mask, truth, use)]), resolution_mm=1.5, svr_iterations=0, config=FAST)
    ss = SliceSet.from_stacks([(vol, mask, truth, use)])
    scrambled = perturb(truth, np.random.default_rng(3), 15.0, 8.0, ss.centres())
    bad = reconstruct(SliceSet.from_stacks([(vol, mask, scrambled, use)]), resolution_mm=1.5, svr_iterations=0,
                      config=FAST)
    g, b = good.quality, bad.quality
    # Agreement hardly tells them apart (the scrambled volume's stray sheets, off the returned volume,
    # take it down a little): the alternate slices do.
    assert g["median_ncc"] > 0.8 and b["median_ncc"] > 0.6
    assert g["leave_one_stack_out"]["median_ncc"] is None
    g_alt, b_alt = g["leave_alternate_slices_out"], b["leave_alternate_slices_out"]
    assert g_alt["median_ncc"] > MIN_ALTERNATE_NCC > b_alt["median_ncc"], (g_alt, b_alt)
    assert g["coherent"] is True and b["coherent"] is False
    assert len(g_alt["even_odd_median_ncc"]) == 2 and g_alt["slices"] > 0.5 * len(truth)


def test_a_stack_placed_where_no_other_stack_reaches_does_not_predict_itself(acquisition) -> None:  # noqa: ANN001
    # Solved from the full volume, the left-out stack's imprint stays wherever no other stack reaches,
    # and its slices predict themselves there; solved from the other stacks' average, they do not.
    placed = [(vol, mask, t, np.ones(len(t), bool)) for (vol, mask), t in zip(acquisition.stacks, acquisition.truth)]
    vol, mask, t, use = placed[1]
    placed[1] = (vol, mask, translate([90.0, 0.0, 0.0]) @ t, use)           # beyond the others' field of view
    res = reconstruct(SliceSet.from_stacks(placed), resolution_mm=2.0, svr_iterations=1, config=FAST)
    assert res.quality["median_ncc"] > 0.8                                   # every stack agrees with itself
    held = res.quality["leave_one_stack_out"]["per_stack_median_ncc"]
    assert held[1] < 0.2 < 0.8 < min(held[0], held[2]), held


def test_slices_a_path_dropped_still_count_when_a_stack_is_left_out() -> None:
    ncc = np.array([0.95, 0.9, 0.92, 0.93])
    held = np.array([0.9, 0.2, 0.88, 0.1])                 # the second and fourth fit nothing
    in_volume = np.array([True, False, True, False])       # the path dropped them
    given = np.ones(4, bool)                               # the job was given all four
    stacks = np.array([0, 0, 1, 1])
    r = quality_report(ncc, held, in_volume, stacks, given)
    assert r["judged_slices"] == 2 and r["median_ncc"] == 0.935
    assert r["leave_one_stack_out"]["per_stack_median_ncc"] == [0.55, 0.49]
    assert r["leave_one_stack_out"]["slices"] == 4                      # what the job's choice weighs its score by
    assert quality_report(ncc, held, in_volume, stacks)["leave_one_stack_out"]["median_ncc"] == 0.89
    assert quality_report(ncc, held, in_volume, stacks)["leave_one_stack_out"]["slices"] == 2
    assert r["coherent"] is True                                         # 0.5, the least a coherent volume scores
    assert quality_report(ncc, held * 0.5, in_volume, stacks, given)["coherent"] is False


def test_left_out_slices_are_judged_as_acquired_not_as_matched(acquisition, monkeypatch) -> None:  # noqa: ANN001
    """Leave one stack out solves with the matched intensities and judges each left-out slice by its
    values as acquired: its shading was fitted to a volume that held it."""
    from service.reconstruction import pipeline

    seen = {}
    real = pipeline.held_out_ncc

    def spy(model, values, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        seen["solved"], seen["judged"] = values, kwargs.get("judged")
        return real(model, values, *args, **kwargs)

    monkeypatch.setattr(pipeline, "held_out_ncc", spy)
    placed = [(vol, mask, t, np.ones(len(t), bool)) for (vol, mask), t in zip(acquisition.stacks, acquisition.truth)]
    ss = SliceSet.from_stacks(placed)
    reconstruct(ss, resolution_mm=1.5, svr_iterations=1, config=FAST)
    np.testing.assert_array_equal(seen["judged"], ss.values)
    assert not np.array_equal(seen["solved"], ss.values)


def test_a_stack_without_an_included_slice_is_no_group_of_the_held_out_score(acquisition) -> None:  # noqa: ANN001
    """A request's stack none of whose slices the job may use (none accepted, or found mirrored) is no
    stack to leave out: the job is judged as the one stack it holds, by its alternate slices (it left
    the empty stack out, and the real stack out of a volume then made of nothing: median 0, incoherent,
    and no frame step ran)."""
    (vol0, mask0), (vol1, mask1) = acquisition.stacks[:2]
    t0, t1 = acquisition.truth[:2]
    alone = reconstruct(SliceSet.from_stacks([(vol0, mask0, t0, np.ones(len(t0), bool))]), resolution_mm=1.5,
                        svr_iterations=0, config=FAST).quality
    with_empty = reconstruct(SliceSet.from_stacks([(vol0, mask0, t0, np.ones(len(t0), bool)),
                                                   (vol1, mask1, t1, np.zeros(len(t1), bool))]),
                             resolution_mm=1.5, svr_iterations=0, config=FAST).quality
    assert with_empty["coherent"] is True and alone["coherent"] is True
    assert with_empty["leave_one_stack_out"] == {"median_ncc": None, "slices": 0, "per_stack_median_ncc": [None, None]}
    assert with_empty["leave_alternate_slices_out"]["median_ncc"] == alone["leave_alternate_slices_out"]["median_ncc"]
