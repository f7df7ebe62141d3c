"""Whether two voxel grids are one: the same voxel centres in the world, however a file stores them.

Tools write one image in different voxel orders (a reorienting tool swaps and reverses axes and
says so in the header), and headers round their placements: a mask or a copy of a stack is on a
stack's grid when its voxel centres lie where the stack's do, within a small tolerance, in any
order of its axes (:func:`in_order_of`).
"""

from __future__ import annotations

import numpy as np
from nibabel import orientations
from numpy.typing import NDArray

from service.io.volume import Volume

GRID_TOLERANCE_VOXELS = 0.01
"""How far (a share of the stack's smallest voxel) a mask's grid may lie from its stack's at the
grid's corners, or :data:`GRID_TOLERANCE_OF_EXTENT` of the grid's diagonal where that is more: a
mask on another grid lies a voxel or more off."""
GRID_TOLERANCE_OF_EXTENT = 1e-4
"""A mask written with a qform alone, beside a stack whose sform is very slightly oblique, cannot
hold that obliqueness in its quaternion: it lies a few micrometres off at the grid's corners, in
proportion to the field of view (a third-party manual mask: 1.5 micrometres on a 300 mm grid;
a 512 x 512 reconstruction of 0.59 mm pixels, 9 micrometres, 0.015 of its voxel)."""


def in_order_of(volume: Volume, reference: Volume) -> Volume | None:
    """``volume`` with its voxels in ``reference``'s order where it holds ``reference``'s grid (the same
    voxel centres in the world: :func:`on_grid`) stored in any order of its axes and their
    directions (``volume`` itself where stored alike); None where it holds another grid.

    Example (a stack stored with its slices reversed, its header saying so; one a slice further on):
        >>> from service.geometry.pose import index_reversal
        >>> stack = Volume(np.arange(12, dtype=np.float32).reshape(2, 2, 3), np.diag([1.0, 1.0, 3.0, 1.0]))
        >>> reversed_k = Volume(stack.array[:, :, ::-1].copy(), stack.affine @ index_reversal(2, 3))
        >>> np.array_equal(in_order_of(reversed_k, stack).array, stack.array)
        True
        >>> further = Volume(stack.array, stack.affine.copy()); further.affine[2, 3] = 3.0
        >>> in_order_of(further, stack) is None
        True
    """
    ornt = orientations.ornt_transform(orientations.io_orientation(volume.affine),
                                       orientations.io_orientation(reference.affine))
    if (ornt == [[0, 1], [1, 1], [2, 1]]).all():                       # already in the reference's order
        same = volume.array.shape == reference.array.shape and on_grid(np.asarray(volume.affine, np.float64), reference)
        return volume if same else None                                # with what its file says of itself
    array = orientations.apply_orientation(np.asarray(volume.array), ornt)
    affine = np.asarray(volume.affine, np.float64) @ orientations.inv_ornt_aff(ornt, volume.array.shape)
    if array.shape != reference.array.shape or not on_grid(affine, reference):
        return None
    return Volume(np.ascontiguousarray(array), affine)     # not what the file says of its own storage (slice order)


def on_grid(affine: NDArray, volume: Volume) -> bool:
    """Whether voxel -> world ``affine`` puts the corners of ``volume``'s voxel grid where its own
    affine does, within :data:`GRID_TOLERANCE_VOXELS` of a voxel (or :data:`GRID_TOLERANCE_OF_EXTENT`
    of the grid's diagonal, where that is more).

    Example (a hundredth of a millimetre off on a 1 mm grid: on it; a tenth: not):
        >>> v = Volume(np.zeros((8, 8, 4), np.float32), np.eye(4))
        >>> on_grid(np.eye(4) + np.eye(4, k=3) * 0.005, v), on_grid(np.eye(4) + np.eye(4, k=3) * 0.1, v)
        (True, False)
    """
    last = np.array(volume.array.shape[:3]) - 1
    corners = np.array([[*(last * bits), 1] for bits in np.ndindex(2, 2, 2)], dtype=np.float64).T
    world = np.asarray(volume.affine, np.float64) @ corners
    diagonal = float(np.linalg.norm(world[:3, -1] - world[:3, 0]))
    tolerance = max(GRID_TOLERANCE_VOXELS * float(np.min(volume.spacing)), GRID_TOLERANCE_OF_EXTENT * diagonal)
    return bool(np.abs(np.asarray(affine, np.float64) @ corners - world).max() <= tolerance)
