"""The two answers' comparison in the mask experiments: their slices joined over the stacks and the
rigid offset common to them recovered about the atlas centre."""

from __future__ import annotations

import numpy as np

from model_export.experiments.frame_bias import about_centre
from model_export.experiments.mask_vote import common_offset
from service.geometry import se3
from service.inference.acceptance import ATLAS_CENTRE_MM


def test_a_common_rigid_offset_of_one_answer_is_recovered_and_nothing_is_left() -> None:
    """Two stacks' slice poses, the second answer the first moved by one rigid offset about the atlas
    centre (3 deg about x, 2 mm along y): the joined slices come back in order, the offset is that
    move, and once it is undone the two answers coincide."""
    rng = np.random.default_rng(0)
    first = [se3.exp(np.c_[rng.normal(0, 0.3, (n, 3)), rng.normal(0, 10, (n, 3))]) for n in (4, 3)]
    offset = se3.exp(np.array([np.radians(3.0), 0.0, 0.0, 0.0, 2.0, 0.0]))
    moved = about_centre(offset, ATLAS_CENTRE_MM)
    pairs = [(p, moved[None] @ p) for p in first]
    a, b, frame, left = common_offset(pairs)
    np.testing.assert_allclose(a, np.concatenate(first))
    np.testing.assert_allclose(frame, offset, atol=1e-9)
    assert np.abs(left).max() < 1e-6


def test_no_pair_means_no_offset() -> None:
    assert common_offset([(np.zeros((0, 4, 4)), np.zeros((0, 4, 4)))]) is None
