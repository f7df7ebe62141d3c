"""A stack as a batch of 2D slices along its slice axis, with each slice's voxel -> slice-frame map.

The slice axis is the voxel axis of largest spacing (ties: the last one), per the API contract.
Each slice is laid out as a picture the same way whatever order the file stores its in-plane voxels
in (:func:`~service.geometry.frames.in_plane_layout`: its columns, slice-frame ``x``, and rows, ``y``,
along the in-plane voxel axes nearest two fixed world axes): a file with its rows reversed or its
in-plane axes swapped shows the network the same pictures. The slice normal is ``z = x cross y``, so
that the slice frame is always a right-handed, physically scaled copy of the stack's geometry.

Example:
    >>> import numpy as np
    >>> from service.io.volume import Volume
    >>> vol = Volume(np.zeros((4, 5, 3), np.float32), np.diag([1.0, 1.0, 4.0, 1.0]))
    >>> s = split_stack(vol, np.ones((4, 5, 3), bool))
    >>> s.slice_axis, s.images.shape, s.pixel_mm
    (2, (3, 5, 4), (1.0, 1.0))
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.geometry import frames
from service.io.acquisition_geometry import SPACING_TIE
from service.io.volume import Volume


@dataclass
class StackSlices:
    """Slices of one stack.

    Attributes:
        images: ``[n, H, W]`` float32, laid out as ``layout`` says.
        masks: ``[n, H, W]`` bool.
        pixel_mm: ``(row_mm, col_mm)``.
        slice_axis: the voxel axis the slices are taken along.
        slice_from_voxel: ``[n, 4, 4]`` voxel index ``(i, j, k, 1)`` -> slice-frame mm of each slice.
        layout: ``(x_axis, y_axis, x_sign, y_sign)``, the voxel axes (and their directions) the
            pictures' columns and rows run along (:func:`~service.geometry.frames.in_plane_layout`).
    """

    images: NDArray[np.float32]
    masks: NDArray[np.bool_]
    pixel_mm: tuple[float, float]
    slice_axis: int
    slice_from_voxel: NDArray[np.float64]
    layout: tuple[int, int, int, int] = (0, 1, 1, 1)

    def to_stack(self, pictures: NDArray) -> NDArray:
        """``[n, H, W]`` arrays laid out as these slices' pictures, back in the stack's voxel order.

        Example (a stack stored with its rows reversed):
            >>> vol = Volume(np.arange(24.0).reshape(2, 4, 3), np.diag([1.0, -1.0, 3.0, 1.0]))
            >>> s = split_stack(vol, np.ones((2, 4, 3), bool))
            >>> s.layout, bool(np.array_equal(s.to_stack(s.images), vol.array))
            ((0, 1, 1, -1), True)
        """
        return stack_from_pictures(pictures, self.slice_axis, self.layout)


def mask_box(mask: NDArray, margin: NDArray | list[int]) -> tuple[slice, ...] | None:
    """The index box of ``mask``'s nonzero voxels grown by ``margin`` voxels per axis, clipped to the
    array (None when the mask is empty).

    Example:
        >>> m = np.zeros((6, 8), bool); m[2, 3:5] = True
        >>> mask_box(m, [1, 2])
        (slice(1, 4, None), slice(1, 7, None))
    """
    m = np.asarray(mask, bool)
    hits = [np.flatnonzero(m.any(axis=tuple(a for a in range(m.ndim) if a != axis))) for axis in range(m.ndim)]
    if not all(len(h) for h in hits):
        return None
    lo = np.maximum(np.array([h[0] for h in hits]) - np.asarray(margin), 0)
    hi = np.minimum(np.array([h[-1] for h in hits]) + np.asarray(margin) + 1, m.shape)
    return tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))


def slice_axis_of(spacing: NDArray) -> int:
    """The axis of largest spacing; ties (within :data:`~service.io.acquisition_geometry.SPACING_TIE`,
    a header's rounding) go to the last axis.

    Example:
        >>> slice_axis_of([1.0, 3.0, 1.0]), slice_axis_of([1.0, 1.0, 0.9999]), slice_axis_of([1.2, 1.2, 1.2])
        (1, 2, 2)
    """
    sp = np.asarray(spacing, dtype=np.float64)
    return int(np.flatnonzero(sp >= sp.max() * (1 - SPACING_TIE))[-1])


def stack_axis(volume: Volume) -> int:
    """The axis ``volume``'s slices lie along: the one it says (a streamed stack), else
    :func:`slice_axis_of` its spacing.

    Example (slices 1 mm apart, pixels of 1.5 mm: only the stream knows which axis is the slices'):
        >>> v = Volume(np.zeros((4, 4, 3)), np.diag([1.5, 1.5, 1.0, 1.0]))
        >>> stack_axis(v), stack_axis(Volume(v.array, v.affine, slice_axis=2))
        (1, 2)
    """
    return slice_axis_of(volume.spacing) if volume.slice_axis is None else int(volume.slice_axis)


def blank_slices(volume: Volume) -> NDArray[np.bool_]:
    """Per slice along the stack's slice axis, whether it holds no image: every pixel one value (a
    slice a scanner or a converter filled with zeros where it had none, or a QC step blanked).

    Example:
        >>> v = Volume(np.random.default_rng(0).random((4, 4, 3), np.float32), np.diag([1.0, 1.0, 3.0, 1.0]))
        >>> v.array[:, :, 1] = 0.0
        >>> blank_slices(v).tolist()
        [False, True, False]
    """
    axis = stack_axis(volume)
    plane = tuple(a for a in range(3) if a != axis)
    return np.asarray(volume.array.max(axis=plane) == volume.array.min(axis=plane))


def slice_images(array: NDArray, affine: NDArray, axis: int,
                 ) -> tuple[NDArray, tuple[float, float], tuple[int, int, int, int]]:
    """``[n, H, W]`` slices of a stack's ``array`` along ``axis``, laid out as pictures by the scanner's
    axes (:func:`~service.geometry.frames.in_plane_layout`, as :func:`split_stack` lays out the pose
    network's slices), their ``(row_mm, col_mm)`` and the layout; a view where it can be. The
    localiser's input (:mod:`~service.preprocess.localiser_inputs`): a file that stores its rows
    reversed or its in-plane axes swapped gives the same pictures, so the same mask.

    Example (the same slices stored with their in-plane axes swapped: the same pictures):
        >>> a = np.random.default_rng(0).random((3, 4, 2))
        >>> swapped = np.array([[0.0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 3, 0], [0, 0, 0, 1]])
        >>> one, two = slice_images(a, np.diag([1.0, 1, 3, 1]), 2), slice_images(a.transpose(1, 0, 2), swapped, 2)
        >>> bool(np.array_equal(one[0], two[0])), one[2], two[2]
        (True, (0, 1, 1, 1), (1, 0, 1, 1))
    """
    layout = frames.in_plane_layout(affine, axis)
    sp = frames.voxel_spacing(affine)
    return pictures(array, axis, layout), (float(sp[layout[1]]), float(sp[layout[0]])), layout


def split_stack(volume: Volume, mask: NDArray, axis: int | None = None) -> StackSlices:
    """Slices, masks and slice-frame transforms of a stack (vectorised, no per-slice loop), along
    ``axis`` (default: :func:`stack_axis`, the one the volume says, else the one its spacing does),
    each slice laid out as :func:`~service.geometry.frames.in_plane_layout` says."""
    a = stack_axis(volume) if axis is None else axis
    layout = frames.in_plane_layout(volume.affine, a)
    x_axis, y_axis, sx, sy = layout
    images = pictures(np.asarray(volume.array, dtype=np.float32), a, layout)
    masks = pictures(np.asarray(mask, dtype=bool), a, layout)
    n, h, w = images.shape
    sp = frames.voxel_spacing(volume.affine)
    order = [x_axis, y_axis, a]
    parity = 1.0 if sum(order[i] > order[j] for i in range(3) for j in range(i + 1, 3)) % 2 == 0 else -1.0
    sz = (np.sign(np.linalg.det(volume.affine[:3, :3])) or 1.0) * sx * sy * parity   # the frame right-handed
    m = np.zeros((n, 4, 4))
    m[:, 0, x_axis] = sx * sp[x_axis]
    m[:, 0, 3] = -sx * sp[x_axis] * (w - 1) / 2.0
    m[:, 1, y_axis] = sy * sp[y_axis]
    m[:, 1, 3] = -sy * sp[y_axis] * (h - 1) / 2.0
    m[:, 2, a] = sz * sp[a]
    m[:, 2, 3] = -sz * sp[a] * np.arange(n)
    m[:, 3, 3] = 1.0
    return StackSlices(images, masks, (float(sp[y_axis]), float(sp[x_axis])), a, m, layout)


def pictures(array: NDArray, axis: int, layout: tuple[int, int, int, int]) -> NDArray:
    """``[n, H, W]`` the slices of a stack's ``array`` along ``axis`` laid out as ``layout`` says
    (:func:`~service.geometry.frames.in_plane_layout`); a view where it can be."""
    x_axis, y_axis, sx, sy = layout
    return np.transpose(np.asarray(array), (axis, y_axis, x_axis))[:, ::sy, ::sx]


def stack_from_pictures(images: NDArray, axis: int, layout: tuple[int, int, int, int]) -> NDArray:
    """The inverse of :func:`pictures`: ``[n, H, W]`` back to the stack's voxel order."""
    x_axis, y_axis, sx, sy = layout
    return np.transpose(np.asarray(images)[:, ::sy, ::sx], np.argsort([axis, y_axis, x_axis]))
