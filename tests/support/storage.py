"""A stack as files that store its voxels in other orders write it: the same voxels in the same places
(:func:`~model_export.experiments.localiser_sweep.stored_as`), and arrays carried between the two grids."""

from __future__ import annotations

import itertools

import numpy as np

from model_export.experiments.localiser_sweep import stored_as  # noqa: F401 - the one rewrite, here for the tests

STORAGES = list(itertools.product([False, True], repeat=3))
"""Every ``(flip0, flip1, swap)``: the eight ways a file can store a stack's two in-plane voxel axes."""


def back_from_stored(array: np.ndarray, flip0: bool, flip1: bool, swap: bool) -> np.ndarray:
    """An array on the grid of :func:`stored_as` (a stack whose slices lie along its last axis) back on
    the original grid."""
    a = np.swapaxes(array, 0, 1) if swap else np.asarray(array)
    for axis, flip in ((1, flip1), (0, flip0)):
        if flip:
            a = np.flip(a, axis)
    return np.ascontiguousarray(a)
