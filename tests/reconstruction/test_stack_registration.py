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
