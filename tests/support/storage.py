"""A stack as files that store its voxels in other orders write it: the same voxels in the same places."""

from __future__ import annotations

import itertools

import numpy as np

from service.io.volume import Volume

STORAGES = list(itertools.product([False, True], repeat=3))
"""Every ``(flip0, flip1, swap)``: the eight ways a file can store a stack's two in-plane voxel axes."""


def stored_as(vol: Volume, flip0: bool, flip1: bool, swap: bool) -> Volume:
    """``vol`` as a file that stores its in-plane voxels another way writes it: the same voxels in the same places."""
    a, aff = np.asarray(vol.array), np.asarray(vol.affine, np.float64).copy()
    for axis, flip in ((0, flip0), (1, flip1)):
        if flip:
            a = np.flip(a, axis)
            index = np.eye(4)
            index[axis, axis], index[axis, 3] = -1.0, a.shape[axis] - 1.0
            aff = aff @ index
    if swap:
        a = np.swapaxes(a, 0, 1)
        aff = aff[:, [1, 0, 2, 3]]
    return Volume(np.ascontiguousarray(a), aff)


def as_stored(array: np.ndarray, flip0: bool, flip1: bool, swap: bool) -> np.ndarray:
    """``array`` of the original stack's grid in the order :func:`stored_as` stores it."""
    return np.asarray(stored_as(Volume(np.asarray(array), np.eye(4)), flip0, flip1, swap).array)


def back_from_stored(array: np.ndarray, flip0: bool, flip1: bool, swap: bool) -> np.ndarray:
    """The inverse of :func:`as_stored`: an array of the stored grid back on the original's."""
    a = np.swapaxes(array, 0, 1) if swap else np.asarray(array)
    for axis, flip in ((1, flip1), (0, flip0)):
        if flip:
            a = np.flip(a, axis)
    return np.ascontiguousarray(a)
