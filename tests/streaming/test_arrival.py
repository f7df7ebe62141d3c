"""A streamed slice's pose alone: the twin its stack's decided model points to, or either twin's
error before; the received neighbours the localiser sees with it."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from service.geometry import anchors, twin
from service.inference.estimator import PoseEstimate
from service.streaming.arrival import WINDOW, neighbours, pose_alone

SAGITTAL = np.array([[0.0, 0, 1, 12], [1, 0, 0, 3], [0, 1, 0, -4], [0, 0, 0, 1]])   # 12 mm right of the plane
INFO = SimpleNamespace()                                                             # nothing calibrated beyond the spread


def _state(pose: np.ndarray, scanner_from_voxel: np.ndarray) -> SimpleNamespace:
    est = PoseEstimate(pose[None], np.zeros(1), np.zeros(1, bool), np.array([0.1]), np.array([2.0]))
    return SimpleNamespace(estimate=est, frame=SimpleNamespace(scanner_from_voxel=scanner_from_voxel),
                           network_from_voxel=np.eye(4)[None])


def test_a_slice_takes_the_twin_its_stack_s_decided_model_points_to() -> None:
    scanner = np.eye(4)
    truth = twin.twin(SAGITTAL)                                    # the network answered the mirror image
    fit = SimpleNamespace(fit=SimpleNamespace(branch_decided=True, atlas_from_scanner=truth @ np.linalg.inv(scanner)))
    out = pose_alone(INFO, _state(SAGITTAL, scanner), fit, None)
    assert out.twinned[0] and anchors.ed(out.poses[0], truth) < 1e-9
    assert out.twin_mass[0] == 0.9                                  # the other branch's MC mass, now the reported one's
    assert out.expected_error_mm[0] == 2.0


def test_before_its_stack_decides_a_slice_s_error_allows_for_either_twin() -> None:
    out = pose_alone(INFO, _state(SAGITTAL, np.eye(4)), None, None)
    d = float(twin.twin_distance_mm(SAGITTAL[None])[0])
    assert not out.twinned[0] and np.allclose(out.poses[0], SAGITTAL)
    assert d > 20 and np.isclose(out.expected_error_mm[0], np.sqrt(2.0 ** 2 + 0.5 * d ** 2))
    undecided = SimpleNamespace(fit=SimpleNamespace(branch_decided=False, atlas_from_scanner=np.eye(4)))
    assert np.isclose(pose_alone(INFO, _state(SAGITTAL, np.eye(4)), undecided, None).expected_error_mm[0],
                      out.expected_error_mm[0])


def test_the_localiser_sees_the_received_contiguous_neighbours() -> None:
    stack = SimpleNamespace(frames={k: f"frame {k}" for k in (0, 1, 2, 3, 5)})
    assert WINDOW == 1
    assert neighbours(stack, 2) == ["frame 1", "frame 2", "frame 3"]
    assert neighbours(stack, 5) == ["frame 5"]                       # slice 4 has not come: alone
    assert neighbours(stack, 0) == ["frame 0", "frame 1"]
