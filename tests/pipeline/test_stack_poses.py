"""One stack's poses through the stack stage as ``/v1/predict`` calls it: which slices may vote."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from service.geometry import se3
from service.geometry.pose import make_pose
from service.inference.estimator import PoseEstimate
from service.pipeline.predict import stack_poses
from tests.consistency.test_stack_fit import stack


def _stack_poses(mean: np.ndarray, network_from_scanner: np.ndarray, degenerate: np.ndarray,
                 mask_fraction: np.ndarray):  # noqa: ANN202
    n = len(mean)
    prepared = SimpleNamespace(prepared=SimpleNamespace(mask_fraction=mask_fraction, inputs=[None] * n),
                               upload=SimpleNamespace(volume=SimpleNamespace(affine=np.eye(4))))
    return stack_poses(PoseEstimate(mean, np.ones(n), degenerate), prepared, network_from_scanner, True, 0.0,
                       np.full(n, 5.0))


def test_a_degenerate_or_empty_slice_does_not_vote_however_far_off_its_network_pose() -> None:
    """A stack of 24 slices with network poses 2 mm / 2 deg off a mild motion, one of them degenerate
    and one empty: moving those two slices' network poses 60 mm and 90 deg away changes no other
    slice's returned pose, and neither is called inconsistent (they did not vote: each receives the
    motion model's pose, the same both times)."""
    rng = np.random.default_rng(8)
    truth, network_from_scanner = stack(rng, "mild", n=24)
    noise = np.array([np.radians(2.0)] * 3 + [2.0] * 3) / np.sqrt(3.0)
    near = truth @ se3.exp(rng.normal(0, 1, (len(truth), 6)) * noise)
    degenerate = np.zeros(len(truth), bool)
    degenerate[9] = True
    mask_fraction = np.full(len(truth), 0.5)
    mask_fraction[15] = 0.0
    far = near.copy()
    far[[9, 15]] = make_pose(se3.so3_exp(np.array([0.0, np.pi / 2, 0.0])), [60.0, 0.0, 0.0]) @ near[[9, 15]]
    a = _stack_poses(near, network_from_scanner, degenerate, mask_fraction)
    b = _stack_poses(far, network_from_scanner, degenerate, mask_fraction)
    assert a.fit is not None and a.fit.decidable
    np.testing.assert_allclose(b.poses, a.poses, atol=1e-9)
    assert not b.inconsistent[[9, 15]].any() and not a.inconsistent.any()
