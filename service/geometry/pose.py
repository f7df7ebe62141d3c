"""Building blocks of the pose convention (see the package docstring).

Example:
    >>> import numpy as np
    >>> xy = slice_pixel_coordinates(3, 2.0)
    >>> xy[0, 0].tolist(), xy[1, 1].tolist(), xy[2, 0].tolist()
    ([-2.0, -2.0], [0.0, 0.0], [-2.0, 2.0])
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def make_pose(rotation: ArrayLike, translation: ArrayLike) -> NDArray[np.float64]:
    """Homogeneous ``[..., 4, 4]`` poses from rotations ``[..., 3, 3]`` and translations ``[..., 3]``."""
    r = np.asarray(rotation, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64)
    shape = np.broadcast_shapes(r.shape[:-2], t.shape[:-1])
    out = np.zeros(shape + (4, 4))
    out[..., :3, :3] = r
    out[..., :3, 3] = t
    out[..., 3, 3] = 1.0
    return out


def pixel_offsets_mm(size: int, pixel_mm: float) -> NDArray[np.float64]:
    """The mm offsets ``[L]`` of the ``L`` pixel centres of a slice's row (or column) from the slice
    frame's origin, ``(k - (L-1)/2) s``: the grid is centred on the origin.

    Example:
        >>> pixel_offsets_mm(4, 2.0).tolist()
        [-3.0, -1.0, 1.0, 3.0]
    """
    return (np.arange(size, dtype=np.float64) - (size - 1) / 2.0) * pixel_mm


def slice_pixel_coordinates(size: int, pixel_mm: float) -> NDArray[np.float64]:
    """In-plane mm coordinates ``[L, L, 2]`` (x, y) of the pixel centres of an ``L x L`` slice.

    ``[r, c] -> (x, y) = ((c - (L-1)/2) s, (r - (L-1)/2) s)`` (:func:`pixel_offsets_mm`).
    """
    idx = pixel_offsets_mm(size, pixel_mm)
    x = np.broadcast_to(idx[None, :], (size, size))
    y = np.broadcast_to(idx[:, None], (size, size))
    return np.stack([x, y], axis=-1)




def translate(offset: ArrayLike) -> NDArray[np.float64]:
    """Homogeneous translations ``[..., 4, 4]`` by ``offset`` ``[..., 3]``."""
    off = np.asarray(offset, dtype=np.float64)
    return make_pose(np.broadcast_to(np.eye(3), off.shape[:-1] + (3, 3)), off)


def index_reversal(axis: int, size: int) -> NDArray[np.float64]:
    """``old_from_new`` voxel indices of an array whose ``axis`` (``size`` voxels) is stored the other
    way: new voxel ``k`` is old voxel ``size - 1 - k``. ``affine @ index_reversal(axis, size)`` is the
    reversed array's affine, every voxel where it was.

    Example (3 slices along z: the new first slice is the old last, at the same place):
        >>> (np.diag([1.0, 1.0, 3.0, 1.0]) @ index_reversal(2, 3) @ [0.0, 0.0, 0.0, 1.0]).tolist()
        [0.0, 0.0, 6.0, 1.0]
    """
    m = np.eye(4)
    m[axis, axis], m[axis, 3] = -1.0, size - 1
    return m


def about_centre(transform: ArrayLike, centre: ArrayLike) -> NDArray[np.float64]:
    """A rigid ``transform`` written about the point ``centre`` (its rotation turns about it, its shift
    moves it) as a map of atlas points: ``T(centre) transform T(centre)^-1``.

    Example (a quarter turn about z written about (10, 0, 0) leaves that point where it is):
        >>> quarter = make_pose([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], [0.0, 0.0, 0.0])
        >>> apply(about_centre(quarter, [10.0, 0.0, 0.0]), [[10.0, 0.0, 0.0], [11.0, 0.0, 0.0]]).round(6).tolist()
        [[10.0, 0.0, 0.0], [10.0, 1.0, 0.0]]
    """
    c = np.asarray(centre, dtype=np.float64)
    return translate(c) @ np.asarray(transform, dtype=np.float64) @ translate(-c)


def apply(transform: ArrayLike, points: ArrayLike) -> NDArray[np.float64]:
    """Apply ``[..., 4, 4]`` transforms to points ``[..., 3]`` (broadcasting)."""
    m = np.asarray(transform, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    if m.ndim == 2:                     # one transform: a single matrix product
        return p @ m[:3, :3].T + m[:3, 3]
    # many: three broadcast multiply-adds (einsum does not vectorise broadcast batches)
    return p[..., 0, None] * m[..., :3, 0] + p[..., 1, None] * m[..., :3, 1] + p[..., 2, None] * m[..., :3, 2] \
        + m[..., :3, 3]
