"""What no stage sees, added to the returned poses' expected errors: the floor and the twin risk."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from service.consistency.stage import StackPoses
from service.geometry import twin
from service.geometry.pose import make_pose
from service.pipeline.predict import add_unseen_errors

SAGITTAL = np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]])      # the slice's normal along the atlas x


def _stack(offsets_mm: list[float], decidable: bool | None) -> StackPoses:
    poses = np.stack([make_pose(SAGITTAL, [x, 3.0, 10.0]) for x in offsets_mm])
    n = len(offsets_mm)
    fit = None if decidable is None else SimpleNamespace(decidable=decidable)
    return StackPoses(poses, np.zeros(n), np.zeros(n, bool), np.zeros(n, bool), fit, np.full(n, 3.0))  # type: ignore[arg-type]


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


def test_the_network_poses_of_an_undecided_stack_and_an_uncalibrated_model_take_the_floor_alone() -> None:
    calibrated = SimpleNamespace(expected_error_floor_mm=2.0, twin_risk_logit=(-1.0, -0.1), symmetry_plane_x_mm=0.0)
    for out, info in ((_stack([5.0, 8.0], decidable=False), calibrated), (_stack([5.0, 8.0], decidable=None), calibrated),
                      (_stack([5.0, 8.0], decidable=True), SimpleNamespace(expected_error_floor_mm=2.0))):
        add_unseen_errors(out, info)
        np.testing.assert_allclose(out.expected_error_mm, np.sqrt(13.0))


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
