"""What no stage sees, added to the returned poses' expected errors: the floor, the request's frame
error, the twin risk and the error of inputs noisier than the network learnt."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from service.consistency.stack_fit import StackFit
from service.consistency.stage import StackPoses
from service.geometry import twin
from service.geometry.pose import make_pose
from service.pipeline.unseen_errors import add_unseen_errors

SAGITTAL = np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]])      # the slice's normal along the atlas x


def _stack(offsets_mm: list[float], decidable: bool | None, **fit_fields: object) -> StackPoses:
    """Sagittal slices at ``offsets_mm`` from the plane, of expected error 3 mm; their stack's fit
    decided its branch by its own slices (``decidable``), or as ``fit_fields`` say."""
    poses = np.stack([make_pose(SAGITTAL, [x, 3.0, 10.0]) for x in offsets_mm])
    n = len(offsets_mm)
    fit = None if decidable is None else StackFit(poses, np.zeros(n, bool), np.zeros(n, bool), np.zeros(n), decidable,
                                                  **{"branch_margin": np.inf, **fit_fields})  # type: ignore[arg-type]
    return StackPoses(poses, np.zeros(n), np.zeros(n, bool), np.zeros(n, bool), fit, np.full(n, 3.0))


def _two_phantom_stacks() -> tuple:
    """The shipped network and two prepared stacks (axial and coronal, 18 slices each) of a phantom brain."""
    from service.core.settings import DEFAULT_MODELS_DIR
    from service.inference.estimator import OnnxPoseEstimator
    from service.inference.model_file import load_model
    from service.io.volume import Volume
    from service.pipeline.prepare import StackUpload, prepare_stack
    from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine

    estimator = OnnxPoseEstimator(load_model(DEFAULT_MODELS_DIR / "default" / "model.onnx"))
    image, mask, atlas_affine = phantom_brain(3)
    prepared = []
    for axis in (2, 1):
        shape = (64, 64, 18) if axis == 2 else (64, 18, 64)
        affine = stack_affine(axis, np.eye(3), 1.2, 3.0, shape)
        img, msk = acquire_stack(image, mask, atlas_affine, affine, shape, axis, np.broadcast_to(np.eye(4), (18, 4, 4)))
        upload = StackUpload(f"s{axis}.nii.gz", Volume(img, affine), Volume(msk.astype(np.uint8), affine))
        prepared.append(prepare_stack(upload, estimator.info, False))
    return estimator, prepared


def test_a_decided_stack_adds_each_slices_twin_risk_times_its_squared_distance_to_the_twin() -> None:
    """Sagittal slices 0, 5 and 30 mm off the plane are 0, 10 and 60 mm from their twins: the first
    gains nothing beyond the floor, the second its chance on the twin times 100 mm^2 (enough to pass
    a 4.5 mm limit no longer), the third less (its chance falls faster than its squared distance grows)."""
    info = SimpleNamespace(expected_error_floor_mm=2.0, twin_risk_logit=(-1.0, -0.1), symmetry_plane_x_mm=0.0)
    out = _stack([0.0, 5.0, 30.0], decidable=True)
    add_unseen_errors(out, info)
    d = np.array([0.0, 10.0, 60.0])
    np.testing.assert_allclose(twin.twin_distance_mm(out.poses), d, atol=1e-9)
    expected = np.sqrt(9.0 + 4.0 + twin.twin_risk(d, (-1.0, -0.1)) * d ** 2)
    np.testing.assert_allclose(out.expected_error_mm, expected)
    assert out.expected_error_mm[0] == np.sqrt(13.0) and out.expected_error_mm[1] > 4.9
    assert out.expected_error_mm[2] < out.expected_error_mm[1] - 0.5


def test_a_slice_whose_branch_nothing_decided_is_on_its_twin_by_even_odds() -> None:
    """The stage off (no fit), an inconsistent stack, a consistent one whose branch neither it nor
    the request decided, one the request took for mirrored, or one whose branch the request took for
    it where it fits the request on neither branch (34 and 39 mm from it; 20 and 90 mm): each slice
    keeps a branch no one could tell, so half its squared distance to the twin is added (sagittal
    slices 5 and 8 mm off the plane: 10 and 16 mm from their twins); one on the plane keeps the floor. A decided stack of an uncalibrated model
    (no twin risk) adds nothing."""
    calibrated = SimpleNamespace(expected_error_floor_mm=2.0, twin_risk_logit=(-1.0, -0.1), symmetry_plane_x_mm=0.0)
    undecided_branch = _stack([5.0, 8.0, 0.0], decidable=True, branch_margin=1.1)
    mirrored = _stack([5.0, 8.0, 0.0], decidable=True, mirrored=True)
    for out in (_stack([5.0, 8.0, 0.0], decidable=False), _stack([5.0, 8.0, 0.0], decidable=None), undecided_branch,
                mirrored):
        add_unseen_errors(out, calibrated)
        np.testing.assert_allclose(out.expected_error_mm, np.sqrt(13.0 + 0.5 * np.array([10.0, 16.0, 0.0]) ** 2))
    decided = _stack([5.0, 8.0], decidable=True)
    add_unseen_errors(decided, calibrated)
    for distances, agrees in (((5.0, 90.0), True), ((34.0, 39.0), False), ((20.0, 90.0), False)):
        taken = _stack([5.0, 8.0], decidable=True, branch_margin=1.1, branch_from_request=True,
                       request_distance_mm=distances)              # the request's other stacks set its branch
        assert taken.fit.agrees_with_request is agrees
        add_unseen_errors(taken, calibrated)
        if agrees:                                                 # where it sits with them: the twin risk alone
            np.testing.assert_allclose(taken.expected_error_mm, decided.expected_error_mm)
        else:                                                      # near them on neither branch: even odds
            np.testing.assert_allclose(taken.expected_error_mm, np.sqrt(13.0 + 0.5 * np.array([10.0, 16.0]) ** 2))
    out = _stack([5.0, 8.0], decidable=True)
    add_unseen_errors(out, SimpleNamespace(expected_error_floor_mm=2.0))
    np.testing.assert_allclose(out.expected_error_mm, np.sqrt(13.0))
    alone = _stack([5.0], decidable=None)                            # a streamed slice whose stack decided
    add_unseen_errors(alone, calibrated, branch_known=True)
    np.testing.assert_allclose(alone.expected_error_mm, np.sqrt(13.0))


def test_a_slice_whose_spread_was_not_measured_has_no_expected_error() -> None:
    """One MC pass measures no spread (variance NaN): the floor alone would read as a confident pose.
    A slice the network never saw (no brain) keeps what its stack's model gives it."""
    from service.inference.estimator import PoseEstimate

    info = SimpleNamespace(expected_error_floor_mm=1.3, twin_risk_logit=None, symmetry_plane_x_mm=0.0)
    est = PoseEstimate(np.tile(np.eye(4), (3, 1, 1)), np.array([np.nan, np.nan, 2.0]), np.zeros(3, bool),
                       spread_mm=np.array([0.0, np.nan, 1.0]))                # seen once, unseen, seen 100 times
    out = _stack([10.0, 20.0, 30.0], decidable=True)
    add_unseen_errors(out, info, est)
    assert np.isnan(out.expected_error_mm[0])
    np.testing.assert_allclose(out.expected_error_mm[1:], np.hypot(3.0, 1.3))


def test_a_stack_noisier_than_the_calibration_gains_its_noise_error_in_quadrature() -> None:
    """A model calibrated with ``noise_error (0.09, 50)``: a stack of input noise 0.05 gains nothing,
    one of 0.15 gains 3 mm in quadrature on every slice (one value for the stack, or one per slice);
    unmeasured noise (NaN) and an uncalibrated model add nothing."""
    info = SimpleNamespace(expected_error_floor_mm=2.0, twin_risk_logit=None, symmetry_plane_x_mm=0.0,
                           noise_error=(0.09, 50.0))
    for noise, extra in ((0.05, 0.0), (0.15, 3.0), (float("nan"), 0.0)):
        out = _stack([10.0, 20.0], decidable=True)
        add_unseen_errors(out, info, input_noise=noise)
        np.testing.assert_allclose(out.expected_error_mm, np.sqrt(9.0 + 4.0 + extra ** 2))
    out = _stack([10.0, 20.0], decidable=True)
    add_unseen_errors(out, info, input_noise=np.array([0.05, 0.15]))
    np.testing.assert_allclose(out.expected_error_mm, [np.sqrt(13.0), np.sqrt(22.0)])
    out = _stack([10.0, 20.0], decidable=True)
    add_unseen_errors(out, SimpleNamespace(expected_error_floor_mm=2.0, symmetry_plane_x_mm=0.0), input_noise=0.3)
    np.testing.assert_allclose(out.expected_error_mm, np.sqrt(13.0))


def test_predict_gives_each_stack_the_noise_error_of_its_own_input_noise() -> None:
    """Two stacks of one request through the shipped network (its fixed MC draws: the same poses
    twice), one measured clean and one measured noisy: only the noisy one's expected errors grow, by
    its noise error in quadrature, and the poses stay where they were."""
    from copy import copy
    from dataclasses import replace

    from service.pipeline.predict import predict
    from service.preprocess.noise import noise_error_mm

    estimator, prepared = _two_phantom_stacks()
    estimator.info = replace(estimator.info, noise_error=None)      # the shipped model's own is set below
    calibrated = copy(estimator)
    calibrated.info = replace(estimator.info, noise_error=(0.09, 50.0))
    noisy = [replace(prepared[0], input_noise=0.03), replace(prepared[1], input_noise=0.15)]
    before, _ = predict(noisy, estimator, 20, estimator.info.variance_threshold)
    after, _ = predict(noisy, calibrated, 20, estimator.info.variance_threshold)
    for b, a, p in zip(before, after, noisy):
        np.testing.assert_allclose(a.poses.poses, b.poses.poses)
        np.testing.assert_allclose(a.poses.expected_error_mm,
                                   np.hypot(b.poses.expected_error_mm, noise_error_mm(p.input_noise, (0.09, 50.0))))
    assert [p.noise_error_mm for p in before] == [0.0, 0.0]
    assert after[0].noise_error_mm == 0.0 and after[1].noise_error_mm == pytest.approx(3.0)
    from service.pipeline.documents import stack_objects

    assert [s["noise"]["expected_error_added_mm"] for s in stack_objects(after)] == [0.0, 3.0]
    grown = after[1].poses.expected_error_mm - before[1].poses.expected_error_mm
    assert np.all(grown[np.isfinite(grown)] > 0.0)              # 3 mm in quadrature


def test_a_stack_no_image_stage_weighed_again_takes_its_misfit_factor_before_the_floor() -> None:
    """Slices whose residuals against the others' prediction are 1.7 times the spread the model
    explains (median): the stage's 3 mm grow by ``1 + MISFIT_GAIN * (1.7 - MISFIT_ONSET)`` before the
    floor is added; a stack the image stage refined keeps its own errors, and so does one whose
    slices agree with their model."""
    from service.consistency.stage import MISFIT_GAIN, MISFIT_ONSET, ImageConsistency

    info = SimpleNamespace(expected_error_floor_mm=2.0, twin_risk_logit=None, symmetry_plane_x_mm=0.0)
    factor = 1.0 + MISFIT_GAIN * (1.7 - MISFIT_ONSET)
    for z, refined, own in (([1.7, 1.7, 0.2], None, 3.0 * factor), ([1.7, 1.7, 0.2], True, 3.0), ([0.5, 0.6, 0.2], None, 3.0)):
        out = _stack([10.0, 20.0, 30.0], decidable=True, residual_z=np.array(z))
        if refined:
            out.image_consistency = ImageConsistency(2, 10, 3, 0.5, 1.0, 0.8)
        add_unseen_errors(out, info)
        np.testing.assert_allclose(out.expected_error_mm, np.hypot(own, 2.0))


def test_the_request_s_frame_error_is_added_in_quadrature_beside_the_floor() -> None:
    out = _stack([10.0, 20.0], decidable=True)
    add_unseen_errors(out, SimpleNamespace(expected_error_floor_mm=2.0, symmetry_plane_x_mm=0.0), frame_mm=6.0)
    np.testing.assert_allclose(out.expected_error_mm, np.sqrt(9.0 + 4.0 + 36.0))


def test_predict_gives_every_stack_the_frame_error_of_the_request_s_network_error() -> None:
    """Two stacks of one request through the shipped network (its fixed MC draws: the same poses
    twice), without and with a frame-error calibration: every slice's expected error grows by the
    same ``slope x (sigma - onset)`` in quadrature, ``sigma`` the slice-weighted RMS of the two
    stacks' network errors; the answer reports both, and each slice's own accept flag (judged
    without the request's frame error) is the one it had without the calibration."""
    from copy import copy
    from dataclasses import replace

    from service.consistency.frame_error import request_network_error_mm
    from service.pipeline.documents import stack_objects
    from service.pipeline.predict import predict

    estimator, prepared = _two_phantom_stacks()
    estimator.info = replace(estimator.info, frame_error=None, max_expected_error_mm=None)
    first, _ = predict(prepared, estimator, 20, 1e9)                  # a limit half of these slices pass
    limit = float(np.median(np.concatenate([p.poses.expected_error_mm for p in first])))
    estimator.info = replace(estimator.info, max_expected_error_mm=limit)
    calibrated = copy(estimator)
    calibrated.info = replace(estimator.info, frame_error=(0.0, 0.3))
    before, _ = predict(prepared, estimator, 20, 1e9)
    after, _ = predict(prepared, calibrated, 20, 1e9)
    sigma = request_network_error_mm([p.poses.fit.noise_mm for p in before],
                                     [int((~p.estimate.degenerate).sum()) for p in before])
    assert np.isfinite(sigma) and sigma > 1.0
    for b, a in zip(before, after):
        np.testing.assert_allclose(a.poses.poses, b.poses.poses)
        np.testing.assert_allclose(a.poses.expected_error_mm, np.hypot(b.poses.expected_error_mm, 0.3 * sigma), rtol=1e-9)
        assert b.frame_error_mm == 0.0 and b.own_reasons is None
        assert a.frame_error_mm == pytest.approx(0.3 * sigma) and a.request_network_error_mm == pytest.approx(sigma)
        assert a.own_reasons == b.reasons
    assert sum(r is None for a in after for r in a.reasons) < sum(r is None for b in before for r in b.reasons)
    frames = [s["frame"] for s in stack_objects(after)]
    assert frames[0] == frames[1] == {"request_network_error_mm": round(sigma, 1),
                                      "expected_error_added_mm": round(0.3 * sigma, 2)}
