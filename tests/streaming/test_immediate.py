"""The immediate answer's two estimates: the placement's expected error, and the network's answer weighed with it."""

from __future__ import annotations

import numpy as np

from service.geometry import se3
from service.geometry.iterators import random_poses
from service.geometry.pose import translate
from service.streaming import immediate


def shifted(xs: list[float]) -> np.ndarray:
    poses = np.stack([np.eye(4)] * len(xs))
    poses[:, 0, 3] = xs
    return poses


def test_the_placement_error_holds_its_own_error_and_where_the_latest_slices_lie() -> None:
    frames, expected = shifted([0.0] * 6), np.full(6, 2.0)
    still = immediate.placement_error_mm(expected, shifted([0.0] * 6), np.eye(4), frames, np.arange(6), np.ones(6, bool))
    assert np.isclose(still, 2.0)                                       # no motion: the stage's own error
    early = shifted([20.0, 20.0, 20.0, 0.0, 0.0, 0.0])                   # the fetus moved early on, lies still now
    late = shifted([0.0, 0.0, 0.0, 20.0, 20.0, 20.0])                    # ... and now it has moved
    arrival = np.arange(6)
    assert np.isclose(immediate.placement_error_mm(expected, early, np.eye(4), frames, arrival, np.ones(6, bool)), 2.0)
    moved = immediate.placement_error_mm(expected, late, np.eye(4), frames, arrival, np.ones(6, bool))
    assert np.isclose(moved, np.hypot(2.0, immediate.MOTION_GAIN * 20.0))
    reversed_arrival = arrival[::-1]                                     # the slices came in the other order
    assert np.isclose(immediate.placement_error_mm(expected, late, np.eye(4), frames, reversed_arrival,
                                                   np.ones(6, bool)), 2.0)
    assert immediate.placement_error_mm(expected, late, np.eye(4), frames, arrival, np.zeros(6, bool)) is None


def test_the_placement_error_composes_the_stack_frames_as_the_truth_is_simulated() -> None:
    rng = np.random.default_rng(3)
    atlas_from_scanner = random_poses(1, rng, centre=(5.0, -10.0, 20.0))[0]
    network_in_scanner = random_poses(8, rng, tz_max_mm=30.0)           # each slice's network frame, scanner mm
    truth = atlas_from_scanner @ network_in_scanner                      # a rigid stack: network frame -> atlas
    network_from_scanner = se3.inverse(network_in_scanner)
    arrival = rng.permutation(8)                                         # received in another order than stored
    expected = np.full(8, 2.0)
    assert np.isclose(immediate.placement_error_mm(expected, truth, atlas_from_scanner, network_from_scanner, arrival,
                                                   np.ones(8, bool)), 2.0, atol=1e-9)
    moved = truth.copy()
    latest = np.argsort(arrival)[-immediate.LATEST_SLICES:]
    moved[latest] = translate([3.0, 0.0, 4.0]) @ truth[latest]          # the fetus moved 5 mm (atlas) lately
    moved[np.argsort(arrival)[0]] = translate([0.0, 40.0, 0.0]) @ truth[np.argsort(arrival)[0]]   # long ago
    error = immediate.placement_error_mm(expected, moved, atlas_from_scanner, network_from_scanner, arrival,
                                         np.ones(8, bool))
    assert np.isclose(error, np.hypot(2.0, immediate.MOTION_GAIN * 5.0), atol=1e-9)


def test_the_weighed_answer_lies_between_the_two_and_is_expected_nearer_than_either_alone() -> None:
    pose, predicted = shifted([2.0])[0], np.eye(4)
    chosen, expected = immediate.with_placement(pose, 2.0, predicted, 4.0)
    assert np.isclose(chosen[0, 3], 2.0 * 0.8, atol=1e-6)               # weights 1/4 and 1/16
    independent = (1 / 2.0 ** 2 + 1 / 4.0 ** 2) ** -0.5
    assert np.isclose(expected, immediate.SHARED_ERROR_FACTOR * independent) and independent < expected
    far = shifted([3.1 * np.hypot(2.0, 4.0)])[0]                         # beyond OUTLIER_SIGMAS combined errors
    chosen, expected = immediate.with_placement(far, 2.0, predicted, 4.0)
    assert np.array_equal(chosen, predicted) and expected == 4.0
    chosen, expected = immediate.with_placement(far, 9.0, predicted, 4.0)   # within, with a larger own error
    assert 0.0 < chosen[0, 3] < far[0, 3]
