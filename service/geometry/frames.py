"""World-frame conversions: the ONE place where LPS (ITK/SimpleITK/DICOM) meets RAS (NIfTI, atlas).

* a voxel -> world affine converts as ``A_ras = F @ A_lps`` with ``F = diag(-1, -1, 1, 1)``;
* a world -> world transform converts as ``T_ras = F @ T_lps @ F`` (``F`` is its own inverse).

Also the affine <-> (origin, spacing, direction) bridge used by the readers, so that no other
module composes these by hand.

Example:
    >>> import numpy as np
    >>> a = affine_from_itk(origin=(1, 2, 3), spacing=(0.5, 0.5, 2), direction=np.eye(3))
    >>> a[:3, 3].tolist(), np.diag(a)[:3].tolist()
    ([-1.0, -2.0, 3.0], [-0.5, -0.5, 2.0])
    >>> o, s, d = itk_from_affine(a)
    >>> o.tolist(), s.tolist()
    ([1.0, 2.0, 3.0], [0.5, 0.5, 2.0])
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
RAS_FROM_LPS = LPS_FROM_RAS  # its own inverse


def ras_affine_from_lps(affine_lps: ArrayLike) -> NDArray[np.float64]:
    """Voxel -> RAS affine from a voxel -> LPS affine."""
    return RAS_FROM_LPS @ np.asarray(affine_lps, dtype=np.float64)


def lps_affine_from_ras(affine_ras: ArrayLike) -> NDArray[np.float64]:
    """Voxel -> LPS affine from a voxel -> RAS affine."""
    return LPS_FROM_RAS @ np.asarray(affine_ras, dtype=np.float64)


def ras_transform_from_lps(transform_lps: ArrayLike) -> NDArray[np.float64]:
    """A world -> world transform written in LPS, rewritten in RAS (``F T F``)."""
    return RAS_FROM_LPS @ np.asarray(transform_lps, dtype=np.float64) @ LPS_FROM_RAS


lps_transform_from_ras = ras_transform_from_lps  # the same conjugation


def affine_from_itk(origin: ArrayLike, spacing: ArrayLike, direction: ArrayLike) -> NDArray[np.float64]:
    """Voxel index ``(i, j, k)`` -> RAS mm affine from ITK's LPS origin, spacing and direction.

    ITK: ``p_lps = origin + direction @ diag(spacing) @ index``.
    """
    a = np.eye(4)
    a[:3, :3] = np.asarray(direction, dtype=np.float64).reshape(3, 3) * np.asarray(spacing, dtype=np.float64)
    a[:3, 3] = np.asarray(origin, dtype=np.float64)
    return ras_affine_from_lps(a)


MAX_SHEAR_COS = 1e-3
"""Voxel axes further from right angles than this (cosine; 0.06 deg) are a sheared grid: a file's
grid is refused, and ITK cannot store it."""


def itk_from_affine(affine_ras: ArrayLike) -> tuple[NDArray, NDArray, NDArray]:
    """Inverse of :func:`affine_from_itk`: (LPS origin, spacing, direction) of a RAS affine. Axes
    within :data:`MAX_SHEAR_COS` of right angles (what a file may hold) get the nearest rotation as
    their direction, which ITK requires.

    Raises:
        ValueError: if the affine has shear beyond that, which ITK cannot store.

    Example (axes 0.03 deg off right angles: stored as right angles):
        >>> a = np.eye(4); a[0, 1] = 5e-4
        >>> direction = itk_from_affine(a)[2]
        >>> bool(np.allclose(direction.T @ direction, np.eye(3), atol=1e-12))
        True
    """
    a = lps_affine_from_ras(affine_ras)
    m = a[:3, :3]
    spacing = np.linalg.norm(m, axis=0)
    direction = m / spacing
    if not float(axes_cosine(direction)) <= MAX_SHEAR_COS:            # NaN (an axis of no length) too
        raise ValueError("affine has shear; cannot be expressed as ITK origin/spacing/direction")
    u, _, vt = np.linalg.svd(direction)
    return a[:3, 3].copy(), spacing, u @ vt


def voxel_spacing(affine: ArrayLike) -> NDArray[np.float64]:
    """Voxel sizes (mm) along i, j, k of a voxel -> world affine."""
    return np.linalg.norm(np.asarray(affine, dtype=np.float64)[:3, :3], axis=0)


def voxels_covering(length_mm: ArrayLike, spacing: ArrayLike) -> NDArray[np.int64]:
    """The whole voxels of ``spacing`` (mm) that cover ``length_mm`` (broadcast): the ratio rounded
    up, a ratio within float rounding of a whole number (a millionth of it) taken as that number. A
    header's float32 rounding of a 1 mm pixel (0.99999994 mm) must not add a voxel to a 20 mm
    margin: the same scan in a float64 header would get another box, and every stage after it
    another answer.

    Example:
        >>> voxels_covering(20.0, np.array([1.0, 0.99999994, 3.3])).tolist()
        [20, 20, 7]
    """
    ratio = np.asarray(length_mm, np.float64) / np.asarray(spacing, np.float64)
    return np.ceil(ratio * (1.0 - 1e-6)).astype(np.int64)


def axes_cosine(axes: ArrayLike) -> NDArray[np.float64]:
    """The largest ``|cos|`` between two columns of each ``[..., 3, 3]`` matrix: 0 for axes at right
    angles (a rigid placement, an acquisition's grid), up to 1 for parallel ones.

    Example:
        >>> float(axes_cosine(np.diag([1.0, 2.0, 3.0]))), round(float(axes_cosine([[1, 1, 0], [0, 1, 0], [0, 0, 1]])), 3)
        (0.0, 0.707)
    """
    a = np.asarray(axes, dtype=np.float64)
    unit = a / np.maximum(np.linalg.norm(a, axis=-2, keepdims=True), 1e-12)
    return np.abs(np.swapaxes(unit, -1, -2) @ unit - np.eye(3)).max(axis=(-2, -1))


def in_plane_layout(affine: ArrayLike, axis: int) -> tuple[int, int, int, int]:
    """``(x_axis, y_axis, x_sign, y_sign)``: how a slice across voxel ``axis`` of a grid ``affine`` is
    laid out as a picture, the same for every order the file stores its in-plane voxels in.

    The picture's columns run along voxel axis ``x_axis`` (increasing where ``x_sign`` is 1, decreasing
    where -1) and its rows along ``y_axis``. Of the four directions the two in-plane voxel axes give
    (each either way), the columns take the one nearest the first world axis in the slice's plane,
    the rows the other voxel axis, the way nearest the second. A file
    that stores the slice's rows reversed or its two in-plane axes swapped describes the same four
    directions, so its pictures come out as another file's of the same slices. The world axis
    nearest the slice's normal is left out; of the other two the lower comes first (an axial slice's
    columns run along x, its rows along y; a sagittal slice's along y and z). Where both voxel axes
    lie as near the first world axis (a grid turned by 45 degrees in its plane), the columns take the
    one nearer the second: a tie the file's storage order never breaks.

    Example (an axial grid stored with its in-plane axes swapped and its rows reversed):
        >>> a = np.array([[0.0, 1.0, 0, 0], [-1.0, 0, 0, 0], [0, 0, 3.0, 0], [0, 0, 0, 1]])
        >>> in_plane_layout(a, 2), in_plane_layout(np.diag([1.0, 1.0, 3.0, 1.0]), 2)
        ((1, 0, 1, -1), (0, 1, 1, 1))
    """
    a = np.asarray(affine, dtype=np.float64)[:3, :3]
    cols = a / np.linalg.norm(a, axis=0)
    p, q = (ax for ax in range(3) if ax != axis)
    normal = np.cross(cols[:, p], cols[:, q])
    first, second = (ax for ax in range(3) if ax != int(np.argmax(np.abs(normal))))   # the world axes in the plane
    along = {ax: np.sign(cols[first, ax]) * cols[:, ax] for ax in (p, q)}          # each axis the way along `first`
    x_axis = max((p, q), key=lambda ax: (round(float(along[ax][first]), 6), round(float(along[ax][second]), 6)))
    y_axis = q if x_axis == p else p
    return x_axis, y_axis, int(np.sign(cols[first, x_axis]) or 1), int(np.sign(cols[second, y_axis]) or 1)
