"""Stack consistency on simulated stack geometry: branch decided, motion-tolerant fit, extreme left alone."""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from model_export.acquisitions import MOTION_LEVELS, interleaved_times, smooth_motion
from service.consistency import fit_stack
from service.geometry.anchors import ed
from service.geometry import iterators, se3, twin
from service.geometry.pose import make_pose, translate
from service.io.volume import Volume
from service.preprocess.stack import split_stack

NOISE = np.array([np.radians(10.0)] * 3 + [10.0] * 3) / np.sqrt(3.0)      # 10 deg / 10 mm RMS


def stack(rng: np.random.Generator, motion: str, n: int = 36, orientation: np.ndarray | None = None):
    """Network-frame truth ``[n, 4, 4]`` and ``network_from_scanner`` of a 3 mm stack through the brain."""
    rot = se3.so3_exp(rng.normal(0, 0.15, 3)) @ (np.eye(3) if orientation is None else orientation)
    centre = np.array([1.0, -3.0, 10.0])
    spacing = np.array([1.0, 1.0, 3.0])
    static = make_pose(rot, centre) @ translate(-(np.array([128, 128, n]) - 1) / 2 * spacing) @ np.diag([*spacing, 1])
    scanner_from_atlas = make_pose(iterators.random_rotations(1, rng, np.pi)[0], rng.uniform(-30, 30, 3))
    affine = scanner_from_atlas @ static
    geo = split_stack(Volume(np.zeros((128, 128, n), np.float32), affine), np.ones((128, 128, n), bool))
    level = MOTION_LEVELS[motion]
    if level is None:
        truth = iterators.random_poses(n, rng, tz_max_mm=0.0, centre=np.zeros(3))
        truth[:, :3, 3] = centre + rng.uniform(-15, 15, (n, 3))
    else:
        moved = translate(centre) @ se3.exp(smooth_motion(interleaved_times(n), rng, *level)) @ translate(-centre)
        truth = moved @ static[None] @ np.linalg.inv(geo.slice_from_voxel)
    return truth, geo.slice_from_voxel @ np.linalg.inv(affine)


def fake_network(truth: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Per slice the truth or its twin (50 %) plus 10 mm / 10 deg of noise; returns (poses, chose_twin)."""
    chose = rng.random(len(truth)) < 0.5
    poses = np.where(chose[:, None, None], twin.twin(truth), truth) @ se3.exp(rng.normal(0, 1, (len(truth), 6)) * NOISE)
    return poses, chose


def shaped_errors(truth: np.ndarray, rng: np.random.Generator, shape: np.ndarray, sd_mm: float) -> np.ndarray:
    """``truth`` with errors of variance ``sd_mm^2 * shape`` per coordinate of each slice's anatomical
    axes (:func:`~service.consistency.error_shape.anatomical_axes`; rotations in mm at the anchor radius)."""
    from service.consistency.error_shape import anatomical_axes
    from service.geometry.anchors import ANCHOR_HALF_SIZE_MM

    r = anatomical_axes(truth[:, :3, :3])
    xi = rng.normal(0, 1, (len(truth), 6)) * np.sqrt(shape) * sd_mm
    return truth @ make_pose(r @ se3.so3_exp(xi[:, :3] / ANCHOR_HALF_SIZE_MM) @ np.swapaxes(r, 1, 2),
                             np.einsum("nij,nj->ni", r, xi[:, 3:]))


@pytest.mark.parametrize("motion", ["mild", "moderate"])
@pytest.mark.parametrize("orientation", ["axial", "coronal", "sagittal"])
def test_branch_decided_and_fit_beats_the_network(motion: str, orientation: str) -> None:
    from model_export.acquisitions import ORIENTATIONS

    rng = np.random.default_rng(zlib.crc32(f"{motion}-{orientation}".encode()))   # not hash(): salted per process
    right, ed_fit, ed_net = [], [], []
    for _ in range(4):
        truth, nk = stack(rng, motion, orientation=ORIENTATIONS[orientation])
        poses, chose = fake_network(truth, rng)
        fit = fit_stack(poses, nk, expected_error_mm=np.full(len(poses), 14.0))
        assert fit.decidable
        distinguishable = ed(truth, twin.twin(truth)) > 20.0      # midline sagittal slices are their own twins
        right.append((ed(fit.poses, truth) < ed(fit.poses, twin.twin(truth)))[distinguishable])
        assert (fit.twinned == chose)[distinguishable].mean() > 0.9    # the network's poses were put on their side
        ed_fit.append(ed(fit.poses, truth))
        ed_net.append(twin.twin_min_ed(poses, truth))                        # the network's twin-min
    assert np.concatenate(right).mean() >= 0.99
    assert np.concatenate(ed_fit).mean() < 0.6 * np.concatenate(ed_net).mean()


def test_extreme_motion_is_undecidable_and_changes_nothing() -> None:
    rng = np.random.default_rng(7)
    for _ in range(3):
        truth, nk = stack(rng, "extreme")
        poses, _ = fake_network(truth, rng)
        fit = fit_stack(poses, nk, expected_error_mm=np.full(len(poses), 14.0))
        assert not fit.decidable
        np.testing.assert_array_equal(fit.poses, poses)
        assert not fit.twinned.any() and not fit.inconsistent.any()


def test_a_gross_outlier_is_flagged_and_given_the_stack_pose() -> None:
    rng = np.random.default_rng(3)
    truth, nk = stack(rng, "mild")
    poses = truth @ se3.exp(rng.normal(0, 1, (len(truth), 6)) * NOISE * 0.3)
    poses[10] = truth[10] @ se3.exp(np.array([0.0, 1.2, 0.0, 30.0, 0.0, 0.0]))   # 69 deg and 30 mm off
    fit = fit_stack(poses, nk, expected_error_mm=np.full(len(poses), 4.0))
    assert fit.decidable and fit.inconsistent[10] and fit.inconsistent.sum() <= 2
    assert ed(fit.poses[10], truth[10]) < 10.0


def test_unusable_slices_take_the_stack_model_and_do_not_vote() -> None:
    rng = np.random.default_rng(5)
    truth, nk = stack(rng, "mild")
    poses = truth @ se3.exp(rng.normal(0, 1, (len(truth), 6)) * NOISE * 0.3)
    usable = np.ones(len(truth), bool)
    usable[:4] = False
    poses[:4] = se3.exp(rng.normal(0, 1, (4, 6)) * [2, 2, 2, 50, 50, 50])      # junk from empty slices
    fit = fit_stack(poses, nk, usable, expected_error_mm=np.full(len(poses), 4.0))
    assert fit.decidable and not fit.inconsistent[:4].any()
    assert ed(fit.poses[:4], truth[:4]).max() < 10.0


def test_the_acquisition_order_is_recognised() -> None:
    rng = np.random.default_rng(11)
    truth, nk = stack(rng, "moderate", n=40)
    poses = truth @ se3.exp(rng.normal(0, 1, (len(truth), 6)) * NOISE * 0.2)
    fit = fit_stack(poses, nk, expected_error_mm=np.full(len(poses), 3.0))
    assert fit.acquisition_order == "interleaved-even-first" and np.isfinite(fit.bandwidth)


def test_branch_margin_tells_a_stack_that_orders_its_slices_from_one_that_does_not() -> None:
    rng = np.random.default_rng(13)
    truth, nk = stack(rng, "mild")
    poses = truth @ se3.exp(rng.normal(0, 1, (len(truth), 6)) * NOISE * 0.3)
    fit = fit_stack(poses, nk, expected_error_mm=np.full(len(poses), 4.0))
    assert fit.decidable and fit.branch_decided and fit.branch_margin > 3.0
    # a network that puts every slice at the stack's centre along the normal: the order is gone
    normal = truth[:, :3, 2]
    offset = np.einsum("ni,ni->n", truth[:, :3, 3] - truth[:, :3, 3].mean(0), normal)
    collapsed = poses.copy()
    collapsed[:, :3, 3] -= offset[:, None] * normal
    fit = fit_stack(collapsed, nk, expected_error_mm=np.full(len(poses), 4.0))
    assert not fit.branch_decided and fit.branch_margin < 1.5


def test_the_whole_stack_on_its_twin_is_put_back() -> None:
    rng = np.random.default_rng(17)
    truth, nk = stack(rng, "mild")
    poses = twin.twin(truth) @ se3.exp(rng.normal(0, 1, (len(truth), 6)) * NOISE * 0.3)   # every slice twinned
    fit = fit_stack(poses, nk, expected_error_mm=np.full(len(poses), 4.0))
    assert fit.twinned.all() and ed(fit.poses, truth).mean() < 5.0


def test_slices_the_network_never_saw_take_the_stack_model_whatever_their_placeholders() -> None:
    """An empty slice is not run (the estimator gives it the identity and a NaN spread): the fit is the
    one it makes when those slices carry any other junk, and they get the stack model's pose and a
    finite expected error."""
    rng = np.random.default_rng(5)
    truth, nk = stack(rng, "mild")
    poses = truth @ se3.exp(rng.normal(0, 1, (len(truth), 6)) * NOISE * 0.3)
    usable = np.ones(len(truth), bool)
    usable[:4] = False
    sd = np.full(len(poses), 4.0)
    junk = fit_stack(np.concatenate([se3.exp(rng.normal(0, 1, (4, 6)) * [2, 2, 2, 50, 50, 50]), poses[4:]]), nk, usable,
                     expected_error_mm=np.where(usable, sd, 40.0))
    poses[:4] = np.eye(4)
    sd[:4] = np.nan
    fit = fit_stack(poses, nk, usable, expected_error_mm=sd)
    assert fit.decidable and not fit.inconsistent[:4].any()
    assert ed(fit.poses[:4], truth[:4]).max() < 10.0 and np.isfinite(fit.expected_error_mm).all()
    assert ed(fit.poses, junk.poses).max() < 0.5


def test_the_expected_error_of_the_returned_poses_is_honest_and_ranks_them() -> None:
    # the outer slices of a stack are where a network is lost, and its spread says so
    rng = np.random.default_rng(19)
    errors, expected = [], []
    for _ in range(6):
        truth, nk = stack(rng, "moderate")
        n = len(truth)
        sd = np.where(np.abs(np.arange(n) - n / 2) > n / 3, 40.0, 6.0)
        poses = truth @ se3.exp(rng.normal(0, 1, (n, 6)) * NOISE * (sd / 14.0)[:, None])
        fit = fit_stack(poses, nk, expected_error_mm=sd)
        assert fit.decidable and fit.expected_error_mm is not None
        errors.append(ed(fit.poses, truth))
        expected.append(fit.expected_error_mm)
    errors, expected = np.concatenate(errors), np.concatenate(expected)
    assert 0.5 < np.sqrt(np.mean(errors ** 2) / np.mean(expected ** 2)) < 2.0
    worst = errors > np.percentile(errors, 80)
    assert expected[worst].mean() > 1.2 * expected[~worst].mean()


def test_errors_unlike_per_coordinate_are_weighed_per_coordinate() -> None:
    """A network that errs mostly in the nodding tilt and along the normal (a measured shape, in each
    slice's anatomical axes): told that shape, the stage follows the motion where the network is
    precise and lands nearer the truth than weighing every coordinate alike."""
    from model_export.acquisitions import ORIENTATIONS

    shape = np.array([3.84, 0.53, 0.18, 0.03, 0.13, 1.30])
    rng = np.random.default_rng(21)
    alike, told = [], []
    for name in ("axial", "coronal", "sagittal"):
        for _ in range(3):
            truth, nk = stack(rng, "moderate", orientation=ORIENTATIONS[name])
            poses = shaped_errors(truth, rng, shape, 5.0)
            sd = np.full(len(poses), 10.0)
            alike.append(ed(fit_stack(poses, nk, expected_error_mm=sd).poses, truth).mean())
            told.append(ed(fit_stack(poses, nk, expected_error_mm=sd, error_shape=shape / shape.mean()).poses, truth).mean())
    assert np.mean(told) < 0.8 * np.mean(alike), (np.mean(told), np.mean(alike))



def test_a_depth_gain_trusts_the_outer_slices_less() -> None:
    """Told that errors outgrow their expected errors towards the stack's ends (``1 + 4 rho^2``), the
    stage's expected errors grow there more than at the middle (which shares a little of it: the
    outer slices' positions pin the stack's tilt at every depth through the lever arm). (On Gaussian
    errors this weighting gains nothing measurable; it is for the network's outer planes, where the
    errors are lost and heavy-tailed.)"""
    from service.consistency.error_shape import relative_depth

    rng = np.random.default_rng(22)
    truth, nk = stack(rng, "moderate")
    sd, shape = np.full(len(truth), 8.0), np.array([3.4, 0.6, 0.23, 0.04, 0.15, 1.6])
    poses = shaped_errors(truth, rng, shape, 4.0)
    plain = fit_stack(poses, nk, expected_error_mm=sd, error_shape=shape)
    told = fit_stack(poses, nk, expected_error_mm=sd, error_shape=shape, depth_gain=4.0)
    rho = relative_depth(np.arange(len(truth), dtype=float), np.ones(len(truth), bool))
    ratio = told.expected_error_mm / plain.expected_error_mm
    assert ratio[rho > 0.8].mean() > 1.15 * ratio[rho < 0.2].mean()
    assert 1.0 <= ratio[rho < 0.2].mean() < 1.35


def test_a_stack_that_cannot_tell_its_branch_takes_the_requests_word(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every slice put on its twin: a stack that does not decide its own branch (here: none does, the
    margin required is out of reach) takes the branch whose rigid fit lies nearer to the placement
    the request's other stacks give (``reference``), whichever that is; without one it is left as it fits."""
    import service.consistency.stack_fit as stack_fit_module

    monkeypatch.setattr(stack_fit_module, "MIN_STACK_BRANCH_MARGIN", 1e9)
    rng = np.random.default_rng(31)
    truth, nk = stack(rng, "mild")
    poses = twin.twin(truth) @ se3.exp(rng.normal(0, 1, (len(truth), 6)) * NOISE * 0.3)
    placement = se3.frechet_mean(truth @ nk)                                  # where the other stacks put the scanner
    told = fit_stack(poses, nk, reference=placement)
    assert told.decidable and told.branch_from_request and not told.branch_decided
    assert told.twinned.all() and ed(told.poses, truth).mean() < 5.0
    mirrored = fit_stack(poses, nk, reference=se3.frechet_mean(twin.twin(truth) @ nk))
    assert not mirrored.twinned.any()
    alone = fit_stack(poses, nk)
    assert not alone.branch_from_request


def test_a_stack_fitted_again_from_its_evidence_gets_the_fit_its_inputs_give(monkeypatch: pytest.MonkeyPatch) -> None:
    """A stack fitted again with the request's word (a reference on either branch, or none) from its
    first fit's ``evidence`` gets exactly the fit its inputs give from the start, and leaves that
    evidence as it was (each fit may be started from it again); a fit keeps its evidence only where
    asked (it holds the motion model's eigendecompositions)."""
    import dataclasses

    import service.consistency.stack_fit as stack_fit_module

    monkeypatch.setattr(stack_fit_module, "MIN_STACK_BRANCH_MARGIN", 1e9)
    rng = np.random.default_rng(31)
    truth, nk = stack(rng, "moderate")
    poses = twin.twin(truth) @ se3.exp(rng.normal(0, 1, (len(truth), 6)) * NOISE * 0.3)
    expected = np.full(len(poses), 6.0)
    first = fit_stack(poses, nk, expected_error_mm=expected, keep_evidence=True)
    assert fit_stack(poses, nk, expected_error_mm=expected).evidence is None
    memo = dict(first.evidence.memo)
    for ref in (se3.frechet_mean(truth @ nk), se3.frechet_mean(twin.twin(truth) @ nk), None):
        fresh = fit_stack(poses, nk, expected_error_mm=expected, reference=ref)
        again = fit_stack(poses, nk, expected_error_mm=expected, reference=ref, evidence=first.evidence)
        for f in dataclasses.fields(fresh):
            if f.compare:
                np.testing.assert_array_equal(getattr(again, f.name), getattr(fresh, f.name), err_msg=f.name)
    assert first.evidence.memo.keys() == memo.keys()
    few = fit_stack(poses[:2], nk[:2], keep_evidence=True)          # too few slices: the network's poses, unfitted
    assert not few.decidable and few.evidence.motion is None
    np.testing.assert_array_equal(fit_stack(poses[:2], nk[:2], evidence=few.evidence).poses, poses[:2])


def test_a_stack_agrees_with_the_request_only_where_it_sits_with_its_stacks(monkeypatch: pytest.MonkeyPatch) -> None:
    """A stack whose branch the request decides agrees with the request when its rigid fit on the
    branch taken lies near the request's placement and its twin far from it; placed 40 mm away (a
    mask run on into the fetal body), it fits the request on neither branch and does not."""
    import service.consistency.stack_fit as stack_fit_module
    from service.geometry.pose import translate

    monkeypatch.setattr(stack_fit_module, "MIN_STACK_BRANCH_MARGIN", 1e9)
    rng = np.random.default_rng(31)
    truth, nk = stack(rng, "mild")
    poses = truth @ se3.exp(rng.normal(0, 1, (len(truth), 6)) * NOISE * 0.3)
    placement = se3.frechet_mean(truth @ nk)
    near = fit_stack(poses, nk, reference=placement)
    taken, other = near.request_distance_mm
    assert near.branch_from_request and near.agrees_with_request and near.branch_known and not near.branch_decided
    assert taken < 5.0 and other > 3 * taken
    far = fit_stack(poses, nk, reference=translate([40.0, 0.0, 0.0]) @ placement)
    assert far.branch_from_request and not far.agrees_with_request and not far.branch_known
    assert far.request_distance_mm[0] > stack_fit_module.REQUEST_AGREEMENT_MM
    alone = fit_stack(poses, nk)
    assert not alone.agrees_with_request and np.isnan(alone.request_distance_mm).all()


def test_independent_errors_pull_the_model_towards_an_error_not_away_from_it() -> None:
    """A still stack whose slices are exact (expected error 1 mm) but two (6 mm off, expected error 8
    mm). With the network's correlated errors allowed, the exact slices beside the two are taken to
    share part of their error, so the model moves *against* it (about -0.5 mm); with independent
    errors (``error_correlations=(0.0,)``, as slices a reconstruction placed have) it stays within
    0.1 mm, on the side of the error."""
    rng = np.random.default_rng(7)
    truth, nk = stack(rng, "mild", n=24)
    still = np.repeat(truth[12:13] @ nk[12:13], 24, axis=0) @ se3.inverse(nk)       # no motion
    off = still.copy()
    off[[6, 17]] = translate(np.array([6.0, 0.0, 0.0])) @ still[[6, 17]]
    errors = np.where(np.isin(np.arange(24), [6, 17]), 8.0, 1.0)
    order = {"sequential": np.arange(24)}
    shift = [float((fit.poses[:, :3, 3] - still[:, :3, 3])[:, 0].mean())
             for fit in (fit_stack(off, nk, expected_error_mm=errors, times=order),
                         fit_stack(off, nk, expected_error_mm=errors, times=order, error_correlations=(0.0,)))]
    assert shift[0] < -0.2 and 0.0 <= shift[1] < 0.1, shift


@pytest.mark.parametrize("motion", ["mild", "moderate"])
def test_where_the_files_put_the_scanners_origin_changes_nothing(motion: str) -> None:
    """The scanner's origin (its table position) is the files' choice, not the fetus's: with every
    slice moved by one shift in scanner mm, the fit returns the same poses, with or without a
    request's reference, and reports its placement and centre in the shifted frame."""
    rng = np.random.default_rng(zlib.crc32(f"origin-{motion}".encode()))
    truth, nk = stack(rng, motion)
    poses, _ = fake_network(truth, rng)
    expected = np.full(len(poses), 14.0)
    reference = se3.frechet_mean(truth @ nk)
    for shift in ([50.0, 0.0, 0.0], [200.0, 150.0, -100.0]):
        moved = translate(-np.array(shift))                    # scanner_from_moved_scanner
        for ref in (None, reference):
            here = fit_stack(poses, nk, expected_error_mm=expected, reference=ref)
            there = fit_stack(poses, nk @ moved, expected_error_mm=expected,
                              reference=None if ref is None else ref @ moved)
            assert here.decidable and there.decidable
            assert ed(here.poses, there.poses).max() < 1e-6
            np.testing.assert_allclose(there.atlas_from_scanner, here.atlas_from_scanner @ moved, atol=1e-6)
            np.testing.assert_allclose(there.centre, here.centre + shift, atol=1e-6)
            np.testing.assert_allclose(there.expected_error_mm, here.expected_error_mm, atol=1e-6)


def test_a_stack_near_the_midline_agrees_with_the_request_where_its_twin_lies_a_little_further() -> None:
    """A sagittal stack whose twin placement is close to its own (the shared real scan's: 14 mm from the
    request on its branch, 18.5 mm on its twin) agrees with the request, as it does with its own
    margin over 1.5; its twin no further than its branch does not; beyond 15 mm on its branch neither."""
    from service.consistency.stack_fit import StackFit

    def fit(taken: float, other: float) -> StackFit:
        return StackFit(np.eye(4)[None], np.zeros(1, bool), np.zeros(1, bool), np.zeros(1), True, branch_margin=1.26,
                        branch_from_request=True, request_distance_mm=(taken, other))

    assert fit(14.0, 18.5).agrees_with_request and fit(14.0, 18.5).branch_known
    assert not fit(14.0, 14.5).agrees_with_request
    assert not fit(16.0, 60.0).agrees_with_request
