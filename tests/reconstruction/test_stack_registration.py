"""Stack-to-stack rigid registration: a stack moved far as a whole is brought back, coarse to fine."""

from __future__ import annotations

import numpy as np

from service.reconstruction.stack_registration import register_stacks, stacks_as_bodies
from service.reconstruction.stack_rigid import fit_stack_rigid
from tests.reconstruction.helpers import CENTRE, pose_error_mm, rigid_about


def test_a_stack_moved_by_8_mm_and_8_deg_is_brought_back(acquisition):
    """Stacks 1 and 2 moved as rigid bodies (8 mm / 8 deg and 5 mm / -6 deg about the brain's
    centre); stack 0 stays. After registration the stacks agree with the truth up to their common
    offset (anchored to the starting transforms): each stack's mean pixel displacement, after that
    offset is removed, is below 0.6 mm (it starts at 6-9 mm)."""
    ss = acquisition.slice_set()
    exact = fit_stack_rigid(ss).atlas_from_scanner
    moves = [np.eye(4), rigid_about(CENTRE, np.array([[5.0, -4.0, 4.0]]), np.array([[6.0, -4.0, 3.0]]))[0],
             rigid_about(CENTRE, np.array([[-4.0, 3.0, 0.0]]), np.array([[-3.0, 0.0, 4.0]]))[0]]
    start = np.stack(moves) @ exact
    result = register_stacks(ss, start)
    bodies = stacks_as_bodies(ss, exact, max_pixels=None)
    before = [pose_error_mm(bodies, start @ bodies.stack_affine, exact @ bodies.stack_affine, np.arange(3) == s)
              for s in range(3)]
    # the common offset: what maps the registered stacks best onto the truth
    from service.reconstruction.registration import anchor_frame

    aligned = anchor_frame(bodies, exact @ bodies.stack_affine, result.atlas_from_scanner @ bodies.stack_affine)
    after = [pose_error_mm(bodies, aligned, exact @ bodies.stack_affine, np.arange(3) == s) for s in range(3)]
    assert max(before) > 6.0
    assert max(after) < 0.6
    assert [lvl for lvl, _ in result.history] == [4.0, 4.0, 2.0, 2.0, 1.0, 1.0]
    assert np.all(result.ncc > 0.8)


def test_one_stack_is_returned_unchanged(acquisition):
    ss = acquisition.slice_set(include=[np.ones(len(t), bool) if i == 0 else np.zeros(len(t), bool)
                                        for i, t in enumerate(acquisition.truth)])
    start = fit_stack_rigid(ss).atlas_from_scanner
    result = register_stacks(ss, start)
    assert np.array_equal(result.atlas_from_scanner, start) and np.all(np.isnan(result.ncc))


def test_stacks_with_motion_inside_are_registered_as_their_slices_lie():
    """Slices moved by 4 deg / 2 mm each (a stack is no longer its file's grid), stacks 1 and 2 then
    moved as wholes. Given the slices' transforms within each stack (``slice_poses``, as the
    stack-consistency stage gives them), registration moves each stack so that its slices land on
    the truth up to the common offset (0.34 mm of mean pixel error from 4.5 mm); the file's grid
    alone, whose stack images are distorted by the motion, leaves 0.77 mm."""
    from service.reconstruction.registration import anchor_frame
    from tests.reconstruction.helpers import make_acquisition

    acq = make_acquisition(3, rot_deg=4.0, trans_mm=2.0)
    ss = acq.slice_set()
    truth = acq.true_poses
    moves = np.stack([np.eye(4), rigid_about(CENTRE, np.array([[5.0, -4.0, 4.0]]), np.array([[6.0, -4.0, 3.0]]))[0],
                      rigid_about(CENTRE, np.array([[-4.0, 3.0, 0.0]]), np.array([[-3.0, 0.0, 4.0]]))[0]])
    moved = moves[ss.stack_index] @ truth
    start = moves @ fit_stack_rigid(ss, truth).atlas_from_scanner

    def error(slice_poses):
        result = register_stacks(ss, start, slice_poses=slice_poses)
        delta = result.atlas_from_scanner @ np.linalg.inv(start)
        found = delta[ss.stack_index] @ moved
        return pose_error_mm(ss, anchor_frame(ss, truth, found), truth)

    before = pose_error_mm(ss, anchor_frame(ss, truth, moved), truth)
    with_motion, file_grid = error(moved), error(None)
    assert before > 4.0
    assert with_motion < 0.6
    assert file_grid > 2.0 * with_motion
