"""The slices a job leaves out, placed by their stack's motion through the slices in its volume:
against a smooth motion and a sudden move simulated here, and the frame a slice without pixels gets;
then registered to the volume from several starts (the phantom itself as the volume)."""

from __future__ import annotations

import numpy as np
import pytest

from service.consistency.slice_order import SliceOrder
from dataclasses import replace

from service.reconstruction.grid import bounds_of, make_grid
from service.reconstruction.left_out import (
    MIN_AREA_MM2,
    REGISTRATION_ITERATIONS,
    REGISTRATION_STEP_MM,
    VolumeReference,
    neighbour_starts,
    place_left_out,
    register_left_out,
)
from service.reconstruction.registration import register_slices
from service.reconstruction.stack_rigid import frame_from_scanner
from tests.reconstruction.helpers import CENTRE, make_acquisition, perturb, pose_error_mm, reference_on, rigid_about

SEQUENTIAL = [SliceOrder.parse("sequential")] * 3


@pytest.fixture(scope="module")
def acquisition():  # noqa: ANN201
    return make_acquisition(3, rot_deg=0.0, trans_mm=0.0)


def moving(acquisition, jump_at: int | None = None) -> tuple:  # noqa: ANN001
    """Each stack's true poses under a smooth motion along its slices (up to 6 deg / 3 mm about the
    brain's centre), with a sudden 8 mm move from slice ``jump_at`` on; the slice set, the truth."""
    ss = acquisition.slice_set()
    n = np.bincount(ss.stack_index)[ss.stack_index].astype(float)
    phase = ss.slice_index / np.maximum(n - 1, 1)
    rotv = np.stack([6.0 * np.sin(np.pi * phase), 3.0 * np.cos(np.pi * phase), np.zeros_like(phase)], 1)
    shift = np.stack([3.0 * phase, np.zeros_like(phase), -2.0 * phase], 1)
    if jump_at is not None:
        shift[ss.slice_index >= jump_at, 1] += 8.0
    return ss, rigid_about(CENTRE, rotv, shift) @ ss.atlas_from_voxel


def left_out_slices(ss, picks: list[int]) -> np.ndarray:  # noqa: ANN001
    """Slices ``picks`` (indices within each stack) of every stack."""
    return np.isin(ss.slice_index, picks)


def test_left_out_slices_follow_a_smooth_motion_and_the_placed_ones_stay(acquisition) -> None:  # noqa: ANN001
    """The volume placed every slice but three a stack to 0.3 mm; the three start 4 mm / 4 deg off
    (their predicted poses, expected error 6 mm) and end within 1 mm of the truth."""
    ss, truth = moving(acquisition)
    rng = np.random.default_rng(0)
    out = left_out_slices(ss, [4, 9, 13])
    refined = perturb(truth, rng, 0.2, 0.3, ss.centres(truth))
    refined[out] = perturb(truth[out], rng, 4.0, 4.0, ss.centres(truth)[out])
    before = pose_error_mm(ss, refined, truth, out)
    placed = place_left_out(ss, refined, ~out, np.where(out, 6.0, 1.0), plane_x_mm=0.0, orders=SEQUENTIAL)
    assert before > 4.0 and pose_error_mm(ss, placed.poses, truth, out) < 1.0, before
    np.testing.assert_array_equal(placed.moved, out)
    np.testing.assert_array_equal(placed.poses[~out], refined[~out])


def test_a_slice_beside_a_sudden_move_takes_its_side_where_its_prediction_tells(acquisition) -> None:  # noqa: ANN001
    """The fetus jumps 8 mm along y at slice 10 of every stack: the model bends across the jump, so
    the slices there are not given its pose. Slice 10, predicted near its truth, takes the pose of
    the placed slice acquired next on its side of the jump (slice 11); slice 9, predicted halfway
    between the two sides, keeps its predicted pose; slice 3, far from the jump, follows the motion."""
    ss, truth = moving(acquisition, jump_at=10)
    rng = np.random.default_rng(1)
    out = left_out_slices(ss, [3, 9, 10])
    refined = perturb(truth, rng, 0.2, 0.3, ss.centres(truth))
    refined[out] = perturb(truth[out], rng, 0.5, 0.5, ss.centres(truth)[out])
    halfway = out & (ss.slice_index == 9)
    refined[halfway, 1, 3] += 4.0
    placed = place_left_out(ss, refined, ~out, np.where(out, 6.0, 1.0), plane_x_mm=0.0, orders=SEQUENTIAL)
    after, far = out & (ss.slice_index == 10), out & (ss.slice_index == 3)
    assert not placed.moved[halfway].any()
    np.testing.assert_array_equal(placed.poses[halfway], refined[halfway])
    assert placed.moved[after].all() and pose_error_mm(ss, placed.poses, truth, after) < 1.5
    np.testing.assert_array_equal(placed.poses[after], placed.poses[out.nonzero()[0] + 1][ss.slice_index[out] == 10])
    assert placed.moved[far].all() and pose_error_mm(ss, placed.poses, truth, far) < 1.0


def test_beside_a_jump_nothing_moves_where_the_motion_is_independent(acquisition) -> None:  # noqa: ANN001
    """Every slice of each stack moved independently (10 mm / 10 deg): no placed slice predicts
    another, so no left-out slice takes a neighbour's pose, however near its prediction lies."""
    ss, truth = moving(acquisition)
    rng = np.random.default_rng(2)
    truth = perturb(truth, rng, 10.0, 10.0, ss.centres(truth))
    out = left_out_slices(ss, [4, 9, 13])
    refined = perturb(truth, rng, 0.2, 0.3, ss.centres(truth))
    refined[out] = refined[np.flatnonzero(out) + 1]                 # each predicted at its next neighbour's pose
    placed = place_left_out(ss, refined, ~out, np.where(out, 6.0, 1.0), plane_x_mm=0.0, orders=SEQUENTIAL)
    assert not placed.moved.any()


def test_slices_without_an_expected_error_or_without_placed_stack_mates_stay(acquisition) -> None:  # noqa: ANN001
    ss, truth = moving(acquisition)
    out = left_out_slices(ss, [5])
    expected = np.where(out, np.nan, 1.0)                  # not posed (an empty slice)
    assert not place_left_out(ss, truth, ~out, expected, plane_x_mm=0.0).moved.any()
    nothing_placed = place_left_out(ss, truth, np.zeros(ss.n_slices, bool), np.full(ss.n_slices, 5.0), plane_x_mm=0.0)
    assert not nothing_placed.moved.any() and np.array_equal(nothing_placed.poses, truth)


def test_left_out_slices_start_from_the_poses_the_job_started_from(acquisition) -> None:  # noqa: ANN001
    """A path that registered a slice and then left it out of its volume gives it a pose nothing
    vouches for: the left-out slices start from the job's starting poses (their expected errors'
    poses); where nothing moves them (here a stack none of whose slices the volume holds) they stay there."""
    ss, truth = moving(acquisition)
    stack_out = ss.stack_index == 2
    astray = truth.copy()
    astray[stack_out, :3, 3] += 25.0                          # the path's registration gone astray
    out = place_left_out(ss, astray, ~stack_out, np.full(ss.n_slices, 5.0), plane_x_mm=0.0, starting=truth)
    assert not out.moved[stack_out].any()
    np.testing.assert_allclose(out.poses[stack_out], truth[stack_out])
    kept = place_left_out(ss, astray, ~stack_out, np.full(ss.n_slices, 5.0), plane_x_mm=0.0)
    np.testing.assert_allclose(kept.poses[stack_out], astray[stack_out])     # without: the path's poses


def test_a_slice_without_pixels_gets_a_frame_on_its_own_plane(acquisition) -> None:  # noqa: ANN001
    """Left out of the volume, a slice has no pixels; its frame's plane ``z = 0`` is still its own
    (the twin mirrors it about that plane), its origin where the stack's pixel centre projects."""
    include = [np.ones(len(t), bool) for t in acquisition.truth]
    include[0][[2, 7]] = False
    ss = acquisition.slice_set(include=include)
    frames = frame_from_scanner(ss)
    empty = np.flatnonzero(ss.pixel_counts() == 0)                 # these two and the phantom's end slices
    assert {2, 7} <= set(ss.slice_index[empty[ss.stack_index[empty] == 0]])
    for k in empty:
        shape = acquisition.stacks[ss.stack_index[k]][0].array.shape
        inplane = [d for d in range(3) if d != ss.slice_axis[k]]
        corners = np.ones((4, 4))
        corners[:, ss.slice_axis[k]] = ss.slice_index[k]
        corners[:, inplane] = [[i, j] for i in (0, shape[inplane[0]] - 1) for j in (0, shape[inplane[1]] - 1)]
        in_frame = corners @ (frames[k] @ ss.stack_affine[k]).T
        np.testing.assert_allclose(in_frame[:, 2], 0.0, atol=1e-9)        # the slice's plane is z = 0
        centre = ss.centres(ss.stack_affine)[ss.stack_index == ss.stack_index[k]]
        seen = ss.pixel_counts()[ss.stack_index == ss.stack_index[k]]
        middle = (centre * seen[:, None]).sum(0) / seen.sum()
        origin = np.linalg.inv(frames[k])[:3, 3]
        assert np.linalg.norm(np.cross(middle - origin, frames[k][2, :3])) < 1e-6   # on the normal through the middle


@pytest.fixture(scope="module")
def imaged():  # noqa: ANN201
    """An acquisition whose images follow its true poses (1 deg / 1 mm per slice), every slice's
    pixels, and the phantom on a 1 mm grid as the job's volume."""
    acq = make_acquisition(0)
    every = acq.slice_set()
    grid = make_grid(1.0, bounds_of(every.positions(), 5.0))
    return acq, every, VolumeReference(reference_on(grid, acq)[0].astype(np.float32), grid, every)


def test_left_out_slices_are_registered_to_the_volume_and_caps_stay(imaged) -> None:  # noqa: ANN001
    """Slices 8 and 9 of every stack start 6 mm / 6 deg off (8 mm expected error) and end within
    0.5 mm of the truth, registered; slice 2 of the first stack (459 mm^2 of brain, a cap) keeps
    the pose the earlier rules left it; without the volume nothing is registered."""
    acq, every, volume = imaged
    truth, rng = acq.true_poses, np.random.default_rng(4)
    cap = (every.stack_index == 0) & (every.slice_index == 2)
    big = np.isin(every.slice_index, [8, 9])
    out = big | cap
    refined = truth.copy()
    refined[out] = perturb(truth[out], rng, 6.0, 6.0, every.centres(truth)[out])
    expected = np.where(out, 8.0, 1.0)
    before = pose_error_mm(every, refined, truth, big)
    placed = place_left_out(every, refined, ~out, expected, plane_x_mm=None, orders=SEQUENTIAL, volume=volume)
    assert every.pixel_counts()[cap] * every.pixel_mm[cap] ** 2 < MIN_AREA_MM2
    assert before > 5.0 and pose_error_mm(every, placed.poses, truth, big) < 0.5, before
    np.testing.assert_array_equal(placed.registered, big)
    assert not (placed.moved & placed.registered).any()
    np.testing.assert_array_equal(placed.poses[~out], refined[~out])
    motion_only = place_left_out(every, refined, ~out, expected, plane_x_mm=None, orders=SEQUENTIAL)
    np.testing.assert_array_equal(placed.poses[cap], motion_only.poses[cap])
    assert not motion_only.registered.any()
    # A volume the job found incoherent places nothing: the slices keep the motion's poses, their
    # NCC with the volume still measured. A job's result says whether its volume is coherent.
    from types import SimpleNamespace
    stacks = [(v, m, p, np.ones(len(p), bool)) for (v, m), p in zip(acq.stacks, acq.truth)]
    for median, coherent in ((0.9, True), (0.2, False)):
        result = SimpleNamespace(volume=SimpleNamespace(array=volume.array), grid=volume.grid,
                                 quality={"leave_one_stack_out": {"median_ncc": median}})
        assert VolumeReference.of(result, stacks).coherent is coherent
    unjudged = place_left_out(every, refined, ~out, expected, plane_x_mm=None, orders=SEQUENTIAL,
                              volume=replace(volume, coherent=False))
    assert not unjudged.registered.any()
    np.testing.assert_array_equal(unjudged.poses, motion_only.poses)
    assert np.isfinite(unjudged.ncc[big]).all() and np.isnan(motion_only.ncc).all()


def test_a_slice_that_fits_the_volume_nowhere_keeps_its_pose(imaged) -> None:  # noqa: ANN001
    """Slice 9 of the first stack, its pixels replaced by noise, registers to no NCC the placed
    slices reach: it keeps its pose while slice 9 of the other stacks is registered."""
    acq, every, volume = imaged
    truth, rng = acq.true_poses, np.random.default_rng(5)
    out = every.slice_index == 9
    noisy = (every.stack_index == 0) & out
    values = every.values.copy()
    at = noisy[every.slice_id]
    values[at] = rng.normal(100.0, 30.0, int(at.sum())).astype(np.float32)
    scrambled = replace(volume, slices=replace(every, values=values))
    refined = truth.copy()
    refined[out] = perturb(truth[out], rng, 3.0, 3.0, every.centres(truth)[out])
    placed = place_left_out(every, refined, ~out, np.where(out, 6.0, 1.0), plane_x_mm=None, orders=SEQUENTIAL,
                            volume=scrambled)
    assert not placed.registered[noisy].any() and placed.registered[out & ~noisy].all()
    # Every slice's NCC at its final pose, by one measure: the noise fits nowhere, the registered
    # slices as the placed ones do.
    np.testing.assert_array_equal(placed.ncc, scrambled.ncc(placed.poses))
    median = np.nanmedian(placed.ncc[~out])
    assert (placed.ncc[noisy] < 0.2 * median).all() and (placed.ncc[out & ~noisy] > 0.9 * median).all()
    assert np.isnan(place_left_out(every, refined, ~out, np.where(out, 6.0, 1.0), plane_x_mm=None).ncc).all()


def test_left_out_slices_already_near_their_pose_are_not_moved_by_the_registration(imaged) -> None:  # noqa: ANN001
    """Slices 8 and 9 of every stack, 0.8 mm / 0.8 deg off: within the registration's scatter, they
    keep their poses (the gain in NCC and the move are too small to trust)."""
    acq, every, volume = imaged
    truth, rng = acq.true_poses, np.random.default_rng(6)
    out = np.isin(every.slice_index, [8, 9])
    poses = truth.copy()
    poses[out] = perturb(truth[out], rng, 0.8, 0.8, every.centres(truth)[out])
    start = poses.copy()
    moved = register_left_out(volume, poses, start, ~out, out, every.stack_index, every.slice_index.astype(float))
    assert not moved.any()
    np.testing.assert_array_equal(poses, start)


def test_a_slice_beyond_the_registrations_reach_is_registered_from_another_start(imaged) -> None:  # noqa: ANN001
    """Slice 9 of every stack, predicted 15 mm / 15 deg off (30 mm expected error: no motion rule
    moves it): registered from that pose alone it settles 10 mm or more from the truth; from the
    other starts it ends within 0.5 mm. The neighbours' starts (the placed slices acquired just
    before and after, their ``atlas_from_voxel`` applied to slice 9's voxels: the stack nearly rigid
    from one slice to the next) put it within 4 mm of the truth here, where the phantom's slices
    move 1 mm / 1 deg each."""
    acq, every, volume = imaged
    truth, rng = acq.true_poses, np.random.default_rng(7)
    out = every.slice_index == 9
    refined = truth.copy()
    refined[out] = perturb(truth[out], rng, 15.0, 15.0, every.centres(truth)[out])
    alone = register_slices(volume.array, volume.grid, every, refined, active=out,
                            max_iterations=REGISTRATION_ITERATIONS, step_mm=REGISTRATION_STEP_MM).atlas_from_voxel
    placed = place_left_out(every, refined, ~out, np.where(out, 30.0, 1.0), plane_x_mm=None, orders=SEQUENTIAL,
                            volume=volume)
    starts = neighbour_starts(refined, ~out, out, every.stack_index, every.slice_index.astype(float))
    for s in range(3):
        one = out & (every.stack_index == s)
        assert pose_error_mm(every, alone, truth, one) > 10.0
        assert placed.registered[one].all() and pose_error_mm(every, placed.poses, truth, one) < 0.5
        for start in starts:
            assert np.isfinite(start[one]).all() and pose_error_mm(every, start, truth, one) < 4.0
