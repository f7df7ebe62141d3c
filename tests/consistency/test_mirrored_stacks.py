"""Stacks whose voxels mirror what their header says: the request finds them, and only them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from service.consistency import mirrored_stacks as mirrored_stacks_module
from service.consistency.mirrored_stacks import SAME_TURN_DEG, mirrored_stacks, relation
from service.geometry import se3, twin
from service.geometry.pose import make_pose

PLANE_X_MM = 1.5


def orthogonal_stacks(rng: np.random.Generator) -> list[np.ndarray]:
    """Three stacks' affines (axial, coronal, sagittal about the scanner's axes; 1.1 mm pixels, 3 mm
    slices, 24 of them, 48 x 48 pixels) turned together by one random rotation."""
    turn = make_pose(se3.exp(np.concatenate([rng.normal(0, 1, 3), np.zeros(3)]))[:3, :3], rng.normal(0, 20, 3))
    affines = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 2, 0)):
        linear = np.eye(3)[:, perm] * np.array([1.1, 1.1, 3.0])
        affines.append(turn @ make_pose(linear, -linear @ np.array([24.0, 24.0, 11.5])))
    return affines


def reflection(affine: np.ndarray, axis: int, about: float) -> np.ndarray:
    """The scanner's reflection that a file makes of its stack by reversing its voxel ``axis`` (``about``
    the voxel coordinate its mirror plane crosses: the middle for reversed voxels, 0 for a lost sign)."""
    flip = np.eye(4)
    flip[axis, axis], flip[axis, 3] = -1.0, 2.0 * about
    return affine @ flip @ np.linalg.inv(affine)


def placements(rng: np.random.Generator, spread_deg: float = 3.0, spread_mm: float = 2.0) -> list[np.ndarray]:
    """One fetus position, and each stack where the fetus was while it was acquired (a few degrees and mm off)."""
    base = se3.exp(np.concatenate([rng.normal(0, 1, 3), rng.normal(0, 10, 3)]))
    return [se3.exp(np.concatenate([rng.normal(0, np.radians(spread_deg), 3), rng.normal(0, spread_mm, 3)])) @ base
            for _ in range(3)]


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("about", ["middle", "first voxel"])
def test_the_stack_whose_voxels_mirror_its_header_is_found_and_no_other(axis: int, about: str) -> None:
    """Each stack in turn reflected along each voxel axis, about its middle (voxels reversed) or its
    first voxel (a lost sign): the stage puts it at ``M A F`` (module docstring); it alone is flagged
    where that turns the brain by :data:`SAME_TURN_DEG` or more (with 10 deg to spare), and nothing
    is flagged where the reflection lies near the head's own mid-sagittal plane (it leaves the
    symmetric brain nearly as it was)."""
    turns = []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        affines = orthogonal_stacks(rng)
        true = placements(rng)
        assert mirrored_stacks(true, [a[:3, :3] for a in affines]) == [False] * 3
        for k in range(3):
            centre = {"middle": (47 if axis < 2 else 23) / 2, "first voxel": 0.0}[about]
            placed = list(true)
            placed[k] = twin.mirror(PLANE_X_MM) @ true[k] @ reflection(affines[k], axis, centre)
            turn = np.degrees(np.linalg.norm(se3.log(placed[k] @ se3.inverse(true[k]))[:3]))
            flags = mirrored_stacks(placed, [a[:3, :3] for a in affines])
            if turn >= SAME_TURN_DEG + 10.0:
                assert flags == [i == k for i in range(3)], (seed, k, turn, flags)
            elif turn < SAME_TURN_DEG:
                assert flags == [False] * 3, (seed, k, turn, flags)
            turns.append(turn)
    assert sum(t >= SAME_TURN_DEG + 10.0 for t in turns) >= 9                   # most draws tell


def test_two_mirror_image_stacks_are_both_flagged_and_a_stack_without_a_decided_branch_is_not() -> None:
    rng = np.random.default_rng(7)
    affines = orthogonal_stacks(rng)
    true = placements(rng)
    placed = [true[0], twin.mirror(PLANE_X_MM) @ true[1] @ reflection(affines[1], 2, 11.5), None]
    assert mirrored_stacks(placed, [a[:3, :3] for a in affines]) == [True, True, False]
    assert mirrored_stacks([true[0], None, None], [a[:3, :3] for a in affines]) == [False] * 3


def test_a_fetus_that_turned_between_stacks_is_not_taken_for_a_mirrored_file() -> None:
    """A stack acquired after the fetus turned by 30-180 deg about any axis (the largest moves between
    stacks): its placement is far from the others', and none of its reflections brings it there,
    except a turn that happens to be one of them -- rare."""
    flagged = tried = 0
    for seed in range(300):
        rng = np.random.default_rng(1000 + seed)
        affines = orthogonal_stacks(rng)
        true = placements(rng)
        axis = rng.normal(0, 1, 3)
        angle = np.radians(rng.uniform(30, 180))
        true[2] = se3.exp(np.concatenate([axis / np.linalg.norm(axis) * angle, rng.normal(0, 5, 3)])) @ true[2]
        kind = relation(true[0], true[2], affines[0][:3, :3], affines[2][:3, :3])
        tried += kind != "same"
        flagged += any(mirrored_stacks(true, [a[:3, :3] for a in affines]))
    assert tried > 250 and flagged <= 0.02 * tried, (flagged, tried)


def test_a_fetus_that_moved_along_its_left_right_axis_is_not_taken_for_a_mirrored_file() -> None:
    """With a stack's axis along the head's left-right axis, the reflection along it is the atlas's
    mirror and a shift: any move along that axis would look like it. A move is no turn: one
    handedness, no flag, whether the axes lie along the head's or a few degrees off."""
    head = np.eye(4)
    for tilt_deg in (0.0, 5.0, 12.0):
        axes = se3.exp(np.array([0.0, 0.0, np.radians(tilt_deg), 0.0, 0.0, 0.0]))[:3, :3] @ np.diag([1.1, 1.1, 3.0])
        for dx in (16.0, 25.0, 40.0):
            moved = se3.exp(np.array([0.0, 0.0, 0.0, dx, 2.0, -1.0])) @ head
            assert relation(head, moved, axes, axes) == "same", (tilt_deg, dx)
            assert mirrored_stacks([head, head, moved], [axes] * 3) == [False] * 3


def test_groups_of_stacks_no_pair_links_are_judged_apart() -> None:
    """A mirrored stack among two that agree, and two more the fetus moved far from (agreeing with
    each other): only the mirrored one is flagged; the far pair has no side in the first group."""
    rng = np.random.default_rng(0)
    affines = orthogonal_stacks(rng)
    true = placements(rng)
    far = se3.exp(np.array([2.0, 0.5, 0.3, 40.0, -30.0, 20.0]))
    placed = [twin.mirror(PLANE_X_MM) @ true[0] @ reflection(affines[0], 2, 11.5), true[1], true[2],
              far @ true[1], far @ true[2]]
    order = [0, 1, 2, 1, 2]
    flags = mirrored_stacks(placed, [affines[i][:3, :3] for i in order])
    assert flags == [True, False, False, False, False]


def test_a_request_of_more_stacks_than_the_exhaustive_search_takes_finds_its_mirrored_ones() -> None:
    """Twenty stacks of one fetus (the three orientations in turn), two of them reflected: those two
    are flagged, and none of the same request without them."""
    rng = np.random.default_rng(3)
    affines = orthogonal_stacks(rng)
    true = [p for _ in range(7) for p in placements(rng)][:20]
    order = [k % 3 for k in range(20)]
    base = se3.exp(np.array([0.4, -0.3, 0.2, 3.0, 1.0, -2.0]))
    placed = [base @ q @ np.linalg.inv(true[0]) for q in true]
    assert mirrored_stacks(placed, [affines[i][:3, :3] for i in order]) == [False] * 20
    for k in (4, 13):
        placed[k] = twin.mirror(PLANE_X_MM) @ placed[k] @ reflection(affines[order[k]], 2, 11.5)
    flags = mirrored_stacks(placed, [affines[i][:3, :3] for i in order])
    assert [k for k, f in enumerate(flags) if f] == [4, 13]


def test_the_large_groups_search_answers_as_the_exhaustive_one_where_the_pairs_agree() -> None:
    """On 200 random groups of 4-12 stacks whose pairs (about half of them known) agree with one
    handedness, the search for large groups flags the same stacks as trying every assignment."""
    rng = np.random.default_rng(7)
    for _ in range(200):
        n = int(rng.integers(4, 13))
        hand = rng.choice([1, -1], n)
        pairs = {(i, j): "same" if hand[i] == hand[j] else "mirrored"
                 for i in range(n) for j in range(i + 1, n) if rng.random() < 0.5}
        for group in mirrored_stacks_module._groups(pairs):
            within = {pair: kind for pair, kind in pairs.items() if pair[0] in group}
            exhaustive = mirrored_stacks_module._smaller_sides(group, within)
            searched = mirrored_stacks_module._smaller_sides(group, within, exhaustive_up_to=0)
            assert searched == exhaustive


def reversed_voxels(s, axis: int):  # noqa: ANN001, ANN201 - a SimulatedStack
    """``s`` with its voxels reversed along ``axis`` (0, 1 in-plane; 2 the slices) and its affine kept,
    and the truth of what each voxel now holds: voxel ``(i, j, k)`` holds what ``(i, j, n - 1 - k)``
    (or ``(w - 1 - i, j, k)``, ...) held, so slice ``k``'s pose is the old pose of the slice it came
    from, composed with that move of the voxel grid (for an in-plane axis, the proper map that also
    turns the slice's normal: it agrees with the reflection on the slice's own plane)."""
    from service.io.volume import Volume

    n, size = len(s.atlas_from_voxel), s.volume.array.shape[axis]
    move = np.tile(np.eye(4), (n, 1, 1))
    if axis == 2:
        old = s.atlas_from_voxel[::-1]
        move[:, 2, 3] = n - 1 - 2 * np.arange(n)                 # k -> n - 1 - k
    else:
        old = s.atlas_from_voxel
        move[:, axis, axis], move[:, axis, 3] = -1.0, size - 1   # i -> size - 1 - i ...
        move[:, 2, 2], move[:, 2, 3] = -1.0, 2 * np.arange(n)    # ... and the normal turned about slice k
    flip = lambda v: Volume(np.flip(v.array, axis).copy(), v.affine)  # noqa: E731
    return replace(s, volume=flip(s.volume), mask=flip(s.mask), atlas_from_voxel=old @ move)


def test_reversed_voxels_are_what_the_truth_says_they_hold() -> None:
    """The simulated truth of a reversed stack: every voxel, placed by its slice's new pose, lands
    where the old pose put the voxel it came from."""
    from model_export.acquisitions import simulate_acquisition
    from tests.support.phantoms import phantom_brain

    img, mask, aff = phantom_brain(0)
    s = simulate_acquisition(img, mask, aff, np.random.default_rng(4), "mild", size=64, pixel_mm=1.6)[0]
    n, (w, h, _) = len(s.atlas_from_voxel), s.volume.array.shape
    for axis in range(3):
        r = reversed_voxels(s, axis)
        for k in (0, n // 2, n - 1):
            for i, j in ((0, 0), (5, 60), (63, 17)):
                src = [i, j, k]
                src[axis] = (w, h, n)[axis] - 1 - src[axis]
                new_place = r.atlas_from_voxel[k] @ [i, j, k, 1.0]
                old_place = s.atlas_from_voxel[src[2]] @ [*src, 1.0]
                assert np.allclose(new_place, old_place), (axis, k, i, j)
                assert np.isclose(np.linalg.det(r.atlas_from_voxel[k][:3, :3]), np.linalg.det(s.atlas_from_voxel[k][:3, :3]))
                assert r.volume.array[i, j, k] == s.volume.array[src[0], src[1], src[2]]


@pytest.mark.parametrize("axis", [2, 1])
def test_a_request_with_one_stack_reversed_answers_its_slices_unaccepted_and_keeps_the_others(axis: int) -> None:
    """Through the predict pipeline (phantom acquisition, an estimator giving each slice's simulated
    truth or twin, as the network sees the slice): one stack's voxels reversed along its slice axis,
    or along its rows, affine kept. Its stack says ``mirrored`` and none of its slices is accepted
    (``inconsistent_with_stack``); the other two stacks are answered as without it."""
    from model_export.acquisitions import simulate_acquisition
    from model_export.evaluate_acquisitions import NoisyTwinEstimator, run_acquisition
    from service.pipeline.documents import stack_objects
    from tests.api.conftest import INFO
    from tests.support.phantoms import phantom_brain

    img, mask, aff = phantom_brain(0)
    stacks = simulate_acquisition(img, mask, aff, np.random.default_rng(4), "mild", size=64, pixel_mm=1.6)
    stacks[0] = reversed_voxels(stacks[0], axis)
    answers, first = [], None
    for request in (stacks, stacks[1:]):
        est = NoisyTwinEstimator(INFO, np.random.default_rng(5), noise_deg=2.0, noise_mm=2.0, other_twin_fraction=0.0)
        (predictions,), _, _ = run_acquisition(request, est, mc_samples=20, bias_correction=False)
        answers.append(stack_objects(predictions))
        first = first or predictions
    reversed_stack = answers[0][0]
    assert reversed_stack["consistency"]["mirrored"] is True
    assert {sl["reason"] for sl in reversed_stack["slices"]} <= {"inconsistent_with_stack", "empty"}
    assert not any(sl["accepted"] for sl in reversed_stack["slices"])
    assert reversed_stack["consistency"]["inconsistent_slices"] == len(reversed_stack["slices"])
    assert reversed_stack["consistency"]["stacks_pooled"] is None               # out of the pooling ...
    assert reversed_stack["consistency"]["image_consistency"] is None            # ... and the image stage
    for with_it, without in zip(answers[0][1:], answers[1]):
        assert with_it["consistency"]["mirrored"] is False
        assert with_it["consistency"]["stacks_pooled"] == without["consistency"]["stacks_pooled"] == 2
        assert with_it["consistency"]["image_consistency"]["stacks"] == 2
        accepted = [sum(sl["accepted"] for sl in a["slices"]) for a in (with_it, without)]
        assert accepted[0] >= 0.8 * len(with_it["slices"]) and abs(accepted[0] - accepted[1]) <= 2, accepted
    # A stream whose later stack's end finds an earlier one mirrored says so in that stack's update.
    from service.streaming.messages import update_messages
    from service.streaming.answers import SliceAnswer

    moved = [SliceAnswer("ax", k, first[0], k) for k in range(3)]
    (update,) = update_messages(moved, consistency=True)
    assert update["consistency"]["mirrored"] is True and not any(sl["accepted"] for sl in update["slices"])
    assert "consistency" not in update_messages(moved)[0]                  # a firm-up's: the stack's own fit
