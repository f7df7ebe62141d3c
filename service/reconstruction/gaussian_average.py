"""The paper's "Gaussian Average": scattered-data interpolation of all slice pixels onto a grid.

Normalised convolution: every pixel is splatted trilinearly at its atlas position (value x weight,
and weight, in one sparse product each), both sums are smoothed with the same Gaussian, and their
ratio is the volume wherever the smoothed weight is large enough. This is the initial volume of
slice-to-volume reconstruction and, from predicted poses, the quick look of the service.

Example:
    >>> import numpy as np
    >>> from service.io.volume import Volume
    >>> from service.reconstruction.slices import SliceSet
    >>> vol = Volume(np.ones((8, 8, 4), np.float32), np.diag([1.0, 1.0, 2.0, 1.0]))
    >>> ss = SliceSet.from_stacks([(vol, None, np.repeat(vol.affine[None], 4, 0), np.ones(4, bool))])
    >>> grid = make_grid(1.0, bounds_of(ss.positions(), 1.0))
    >>> avg = gaussian_average(ss, ss.atlas_from_voxel, grid)
    >>> round(float(avg.volume[avg.support].mean()), 3)
    100.0
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from service.reconstruction.grid import Grid, bounds_of, interpolation_matrix, make_grid
from service.reconstruction.slices import SliceSet

__all__ = ["GaussianAverage", "bounds_of", "compact_brain", "default_sigma_mm", "gaussian_average", "make_grid",
           "splat"]

SUPPORT_FRACTION = 0.1
"""Voxels whose smoothed weight is below this fraction of the (robust) maximum are left empty."""
COMPACT_RADIUS_MM = 3.0
"""What sticks out of a reconstructed brain thinner than twice this is cleared (:func:`compact_brain`)."""
COMPACT_MARGIN_MM = 1.5
""":func:`compact_brain` keeps the support this close to the brain's opened body."""


@dataclass
class GaussianAverage:
    """Result of :func:`gaussian_average`.

    Attributes:
        volume: ``[I, J, K]`` float32 intensities (0 outside ``support``).
        weight: ``[I, J, K]`` smoothed splatting weight (the local data density).
        support: ``[I, J, K]`` bool, where the volume is defined.
    """

    volume: NDArray[np.float32]
    weight: NDArray[np.float32]
    support: NDArray[np.bool_]


def default_sigma_mm(slices: SliceSet, resolution_mm: float) -> float:
    """Smoothing width: half the median slice thickness, at least the output resolution."""
    thick = slices.thickness_mm[slices.include] if slices.include.any() else slices.thickness_mm
    return max(0.5 * float(np.median(thick)), float(resolution_mm))


def splat(points: NDArray, values: NDArray, grid: Grid) -> NDArray[np.float32]:
    """Trilinear splatting (the adjoint of trilinear sampling) of ``values [N]`` at atlas ``points [N, 3]``."""
    mat = interpolation_matrix(grid.voxel_of(points)[:, None, :], grid.shape)
    return (mat.T @ np.asarray(values, dtype=np.float32)).reshape(grid.shape)


def gaussian_average(slices: SliceSet, atlas_from_voxel: ArrayLike, grid: Grid, *, sigma_mm: float | None = None,
                     pixel_weight: NDArray | None = None,
                     support_fraction: float = SUPPORT_FRACTION) -> GaussianAverage:
    """Gaussian-weighted average of all pixels at their atlas positions.

    Args:
        slices: the slice set.
        atlas_from_voxel: ``[n, 4, 4]`` slice transforms.
        grid: output grid (see :func:`make_grid`, :func:`bounds_of`).
        sigma_mm: Gaussian standard deviation (default :func:`default_sigma_mm`).
        pixel_weight: optional ``[N]`` non-negative weights (e.g. robust weights; 0 drops a pixel).
        support_fraction: the volume is set where the smoothed weight exceeds this fraction of its
            99th percentile.

    Returns:
        The :class:`GaussianAverage`.
    """
    sigma = default_sigma_mm(slices, float(grid.spacing.min())) if sigma_mm is None else float(sigma_mm)
    w = np.ones(slices.n_pixels, np.float32) if pixel_weight is None else np.asarray(pixel_weight, np.float32)
    mat = interpolation_matrix(grid.voxel_of(slices.positions(atlas_from_voxel))[:, None, :], grid.shape)
    num = (mat.T @ (w * slices.values)).reshape(grid.shape)
    den = (mat.T @ w).reshape(grid.shape)
    sig_vox = sigma / grid.spacing
    num = ndimage.gaussian_filter(num, sig_vox, mode="constant", truncate=3.0)
    den = ndimage.gaussian_filter(den, sig_vox, mode="constant", truncate=3.0)
    positive = den[den > 0]
    ref = float(np.percentile(positive, 99)) if positive.size else 0.0
    support = den > support_fraction * ref if ref > 0 else np.zeros(grid.shape, bool)
    vol = np.zeros(grid.shape, np.float32)
    vol[support] = num[support] / den[support]
    return GaussianAverage(vol, den.astype(np.float32), support)


def compact_brain(volume: NDArray, spacing: ArrayLike, radius_mm: float = COMPACT_RADIUS_MM) -> NDArray:
    """``volume`` with what lies outside the brain's compact body set to 0.

    A slice whose mask ran on past the skull (the localiser's, at a face or a neck) adds a thin
    sheet or spike to the volume's support where no other slice confirms it. The support (the
    nonzero voxels) is opened by a ball of ``radius_mm`` (by exact distances on the voxel sizes
    ``spacing``: what is thinner than twice the radius goes), its largest connected piece kept, and
    with it every voxel of the support within :data:`COMPACT_MARGIN_MM` of that piece (the opening
    rounds the body's own edges off by about a voxel; a spike keeps a stub of that length). A volume
    whose support the opening empties is returned as it is.

    Example (a 20 mm cube with a 2 mm spike 8 mm long: the spike goes but for a 2 mm stub, the cube
    stays but for 4 voxels at each corner):
        >>> v = np.zeros((40, 40, 40), np.float32); v[10:30, 10:30, 10:30] = 1.0; v[19:21, 19:21, 30:38] = 1.0
        >>> out = compact_brain(v, (1.0, 1.0, 1.0))
        >>> out[20, 20, 30:38].tolist(), int(out[10:30, 10:30, 10:30].sum())
        ([1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], 7968)
    """
    support = np.asarray(volume) != 0
    spacing = np.asarray(spacing, np.float64)
    inside = ndimage.distance_transform_edt(support, sampling=spacing) > radius_mm
    if not inside.any():
        return volume
    opened = support & (ndimage.distance_transform_edt(~inside, sampling=spacing) <= radius_mm + 1e-6)
    labels, _ = ndimage.label(opened)
    body = labels == int(np.argmax(np.bincount(labels.ravel())[1:])) + 1
    kept = support & (ndimage.distance_transform_edt(~body, sampling=spacing) <= COMPACT_MARGIN_MM + 1e-6)
    return np.where(kept, volume, np.zeros((), np.asarray(volume).dtype))
