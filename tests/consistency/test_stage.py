"""The stage's composition against simulated truth: network_from_scanner built from the service's own
crop/centre and the file's geometry gives back the stack's true atlas_from_scanner."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from service.consistency.stack_fit import StackFit
from service.consistency.stage import (
    StackPoses,
    checked_branch,
    consistent_poses,
    network_from_voxel,
    request_reference,
    undecided,
)
from service.pipeline.documents import stack_report
from service.geometry import anchors, se3, twin
from service.geometry.pose import make_pose, translate
from service.io.volume import Volume
from service.preprocess.stack import split_stack


@pytest.mark.parametrize("handedness", [1.0, -1.0])
def test_atlas_from_scanner_is_recovered_from_slice_poses(handedness: float) -> None:
    rng = np.random.default_rng(21)
    n = 24
    direction = se3.so3_exp(np.array([0.3, -0.5, 0.8])) @ np.diag([handedness, 1.0, 1.0])   # oblique, maybe left-handed
    affine = make_pose(direction, [-40.0, 25.0, 10.0]) @ np.diag([0.9, 0.9, 3.2, 1.0])
    geo = split_stack(Volume(np.zeros((80, 80, n), np.float32), affine), np.ones((80, 80, n), bool))
    centroids = np.concatenate([rng.uniform(-15, 15, (n, 2)), np.zeros((n, 1))], 1)       # the service's crops
    nfv = network_from_voxel(translate(centroids), geo.slice_from_voxel)
    atlas_from_scanner = make_pose(se3.so3_exp(rng.normal(0, 1, 3)), rng.uniform(-30, 30, 3))
    truth = atlas_from_scanner @ affine @ np.linalg.inv(nfv)                                # network frame -> atlas
    assert np.allclose(np.linalg.det(truth[:, :3, :3]), 1.0)                               # rigid, whatever the file

    poses = truth.copy()
    poses[::2] = twin.twin(truth[::2])                                                      # half on the other twin
    out = consistent_poses(poses, np.full(n, 0.1), nfv, affine, np.ones(n, bool), 0.0, np.full(n, 0.5))
    report = stack_report(out)
    assert report["decidable"] and report["branch_decided"]
    np.testing.assert_allclose(report["atlas_from_scanner"], atlas_from_scanner, atol=1e-6)
    np.testing.assert_array_equal(out.twinned, np.arange(n) % 2 == 0)
    assert anchors.ed(out.poses, truth).max() < 1e-6
    np.testing.assert_allclose(out.twin_mass, np.where(out.twinned, 0.9, 0.1))


def test_the_request_reference_is_the_precision_weighted_placement_of_the_decided_stacks() -> None:
    undecided_one = placed(translate([50.0, 0.0, 0.0]), 0.1, 1.1)           # precise, but its branch is open
    assert undecided(undecided_one) and not undecided(placed(np.eye(4), 1.0, 3.0))
    told = placed(np.eye(4), 1.0, 0.5)
    told.fit.branch_from_request = True                                   # the request decided it already
    assert not undecided(told)
    assert not undecided(replace(undecided_one, apart_mm=100.0))          # another fetus's: not the request's
    assert request_reference([undecided_one]) is None
    ref = request_reference([placed(np.eye(4), 1.0, 3.0), placed(translate([3.0, 0.0, 0.0]), 2.0, 2.0), undecided_one])
    np.testing.assert_allclose(ref[:3, 3], [0.6, 0.0, 0.0], atol=1e-6)     # weights 1 and 1/4


def placed(atlas_from_scanner: np.ndarray, sd_mm: float, margin: float, centre=(0.0, 0.0, 0.0)) -> StackPoses:
    """A stack the stage fitted at ``atlas_from_scanner`` (its slices' centre ``centre``, scanner mm)."""
    fit = StackFit(np.eye(4)[None], np.zeros(1, bool), np.zeros(1, bool), np.zeros(1), True, atlas_from_scanner,
                   1.0, branch_margin=margin, placement_sd_mm=sd_mm, centre=np.asarray(centre, np.float64))
    return StackPoses(fit.poses, np.zeros(1), fit.twinned, fit.inconsistent, fit)


def test_the_request_reference_does_not_depend_on_the_scanners_origin() -> None:
    """Two stacks placed 20 deg apart, turned about their common centre: their reference is there
    where the two turns cancel, and found with every stack moved by one shift in scanner mm it is
    the unshifted one moved alike (the mean of rigid maps taken about the scanner's origin, 300 mm
    away, would not be)."""
    rng = np.random.default_rng(4)
    centres = np.array([[10.0, -5.0, 20.0], [14.0, -2.0, 16.0]])
    centre = centres.mean(axis=0)
    base = make_pose(se3.so3_exp(rng.normal(0, 1, 3)), [3.0, -4.0, 5.0])
    turns = [se3.so3_exp(np.radians([0.0, 0.0, a])) for a in (-10.0, 10.0)]
    placements = [base @ translate(centre) @ make_pose(t, [0.0, 0.0, 0.0]) @ translate(-centre) for t in turns]
    ref = request_reference([placed(a, 1.0, 3.0, c) for a, c in zip(placements, centres)])
    shift = np.array([200.0, 150.0, -100.0])
    moved = translate(-shift)                                              # scanner_from_moved_scanner
    there = request_reference([placed(a @ moved, 1.0, 3.0, c + shift) for a, c in zip(placements, centres)])
    np.testing.assert_allclose(ref, base, atol=1e-6)
    np.testing.assert_allclose(there, ref @ moved, atol=1e-6)


def test_the_other_stacks_overrule_a_stack_that_decided_its_branch_weakly(monkeypatch: pytest.MonkeyPatch) -> None:
    """A stack decides its branch by its slices' order (every network pose on its twin: the stage
    takes the true branch). Where its margin is under the one checked (here set to twice its own),
    the other stacks placed on the mirrored side overrule it: it takes their branch, sits where they
    do (0.8 mm) and 100 mm from them on its own. Placed where its own branch puts it, or absent,
    they leave it as it was; with the shipped margin (a stack decided by far more) they are not asked."""
    import service.consistency.stage as stage_module
    from tests.consistency.test_stack_fit import NOISE, stack

    rng = np.random.default_rng(32)
    truth, nk = stack(rng, "mild")
    n = len(truth)
    poses = twin.twin(truth) @ se3.exp(rng.normal(0, 1, (n, 6)) * NOISE * 0.3)
    args = (poses, np.full(n, 0.1), nk, np.eye(4), np.ones(n, bool), 0.0, np.full(n, 3.0))
    alone = consistent_poses(*args)
    assert alone.fit.branch_decided and alone.twinned.all() and anchors.ed(alone.poses, truth).mean() < 5.0
    asked: list[float] = []

    def refit(reference: np.ndarray, margin: float) -> StackPoses:
        asked.append(margin)
        return consistent_poses(*args, reference=reference, request_margin=margin)

    mirrored, true_side = se3.frechet_mean(twin.twin(truth) @ nk), se3.frechet_mean(truth @ nk)
    assert checked_branch(alone, mirrored, refit) is alone and not asked            # decided: not asked
    monkeypatch.setattr(stage_module, "CHECKED_MARGIN", alone.fit.branch_margin * 2.0)
    redo = checked_branch(alone, mirrored, refit)
    taken, other = redo.fit.request_distance_mm
    assert asked == [alone.fit.branch_margin * 2.0] and redo is not alone
    assert redo.fit.branch_from_request and not redo.twinned.any() and taken < 2.0 and other > 50.0
    assert anchors.ed(redo.poses, truth).mean() > 50.0
    assert checked_branch(alone, true_side, refit) is alone and len(asked) == 2    # asked, agrees with it
    assert checked_branch(alone, None, refit) is alone and len(asked) == 2          # no other stack
    other_fetus = replace(alone, apart_mm=100.0)
    assert checked_branch(other_fetus, mirrored, refit) is other_fetus and len(asked) == 2   # not the request's


def test_slices_that_move_on_their_own_raise_the_misfit_factor_and_it_makes_their_errors_more_honest() -> None:
    """The same stacks and network errors (4 deg / 3 mm), the fetus drifting smoothly or every slice
    moving on its own within 20 deg / 8 mm: the second's slices disagree with their motion model
    beyond its spreads, so its factor is larger in every stack, and its expected errors times the
    factor lie nearer the true errors than without."""
    from model_export.acquisitions import interleaved_times, motion_twists
    from service.consistency import fit_stack
    from service.consistency.stage import misfit_factor
    from tests.consistency.test_stack_fit import stack

    noise = np.array([np.radians(4.0)] * 3 + [3.0] * 3) / np.sqrt(3.0)
    centre = np.array([1.0, -3.0, 10.0])
    factors, ratios = {}, []
    for seed in range(5):
        for motion in ("mild", "independent"):
            rng = np.random.default_rng(seed)
            truth, nfs = stack(rng, "mild", n=30)
            moved = translate(centre) @ se3.exp(motion_twists(interleaved_times(30), rng, motion)) @ translate(-centre) @ truth
            noisy = moved @ se3.exp(rng.normal(0, 1, (30, 6)) * noise)
            fit = fit_stack(noisy, nfs, expected_error_mm=np.full(30, np.sqrt(np.mean(anchors.ed(noisy, moved) ** 2))))
            factors[seed, motion] = misfit_factor(fit)
            if motion == "independent":
                err = np.sqrt(np.mean(anchors.ed(fit.poses, moved) ** 2))
                ratios.append((err / np.sqrt(np.mean(fit.expected_error_mm ** 2)), err / np.sqrt(np.mean((fit.expected_error_mm * factors[seed, motion]) ** 2))))
    assert all(factors[s, "independent"] > factors[s, "mild"] + 0.2 for s in range(5)), factors
    before, after = np.median(ratios, axis=0)
    assert before > 2.0 and abs(np.log(after)) < 0.6 * abs(np.log(before)), ratios


def test_empty_slices_leave_a_stacks_misfit_factor_as_its_slices_with_brain_give_it() -> None:
    """A whole-uterus stack's end slices show no brain: the network never saw a brain there and
    their 'poses' are no measurement (here: anywhere within 60 mm and 90 deg). They do not vote, get
    no residual, and the stack's factor is the one its slices with brain give it alone."""
    from service.consistency import fit_stack
    from service.consistency.stage import misfit_factor
    from tests.consistency.test_stack_fit import stack

    noise = np.array([np.radians(4.0)] * 3 + [3.0] * 3) / np.sqrt(3.0)
    for seed in range(3):
        rng = np.random.default_rng(seed)
        truth, nfs = stack(rng, "mild", n=30)
        noisy = truth @ se3.exp(rng.normal(0, 1, (30, 6)) * noise)
        expected = np.full(30, np.sqrt(np.mean(anchors.ed(noisy, truth) ** 2)))
        brain = np.arange(30) >= 8                                      # eight empty slices at one end
        junk = noisy.copy()
        junk[~brain] = se3.exp(np.concatenate([rng.uniform(-1.5, 1.5, (8, 3)), rng.uniform(-60, 60, (8, 3))], 1))
        whole = fit_stack(junk, nfs, usable=brain, expected_error_mm=np.where(brain, expected, np.nan))
        alone = fit_stack(noisy[brain], nfs[brain], expected_error_mm=expected[brain])
        assert np.isnan(whole.residual_z[~brain]).all() and np.isfinite(whole.residual_z[brain]).all()
        assert misfit_factor(whole) == pytest.approx(misfit_factor(alone), rel=0.05)
