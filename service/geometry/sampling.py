"""The slice forward model shared by training and reconstruction.

A slice with pose ``P`` (slice mm -> atlas mm, see the package docstring) is sampled from a volume
given as an array indexed ``[i, j, k]`` and its voxel -> world (RAS) affine. All slices of a call
are sampled in one vectorised ``map_coordinates`` call per plane of the through-plane PSF.

Example:
    >>> import numpy as np
    >>> vol = np.zeros((9, 9, 9)); vol[:, :, 4] = 1.0                 # a plane z = 0
    >>> aff = np.eye(4); aff[:3, 3] = -4.0                              # voxel (4,4,4) at origin
    >>> sl = sample_slices(vol, aff, np.eye(4)[None], size=5, pixel_mm=1.0)
    >>> sl.shape, float(sl.min())
    ((1, 5, 5), 1.0)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage, sparse

from service.geometry.pose import apply, make_pose, pixel_offsets_mm, slice_pixel_coordinates

FWHM_TO_SIGMA = 1.0 / (2.0 * np.sqrt(2.0 * np.log(2.0)))
INPLANE_FWHM_FACTOR = 1.2
"""In-plane PSF FWHM as a multiple of the acquisition pixel size (Kainz et al. 2015)."""


def linear_operator(coords: ArrayLike, n_in: int, dtype: type = np.float32) -> sparse.csr_matrix:
    """Linear interpolation of an axis of ``n_in`` samples at ``coords`` (indices; the nearest sample
    beyond the ends) as a sparse ``[len(coords), n_in]`` matrix: :func:`scipy.ndimage.map_coordinates`
    applied to the identity, so that a grid is resampled axis by axis with one product per axis.

    Example:
        >>> linear_operator([0.25, 1.0, 3.0], 3).toarray().tolist()
        [[0.75, 0.25, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    """
    rows, cols = np.meshgrid(np.asarray(coords, np.float64), np.arange(n_in, dtype=np.float64), indexing="ij")
    dense = ndimage.map_coordinates(np.eye(n_in, dtype=dtype), [rows, cols], order=1, mode="nearest")
    return sparse.csr_matrix(dense)


def slice_voxel_coordinates(voxel_from_slice: ArrayLike, size: int, pixel_mm: float,
                            offset_mm: float = 0.0) -> NDArray[np.float64]:
    """Voxel coordinates ``[3, B, L, L]`` of the pixel centres of slices ``voxel_from_slice [B, 4, 4]``
    (slice mm -> voxel indices), ``offset_mm`` along their normals: the layout
    :func:`scipy.ndimage.map_coordinates` takes. A plane's points are its origin plus multiples of
    its two in-plane axes, so they are summed from a row and a column of the grid (no per-point
    matrix product).

    Example:
        >>> vfs = np.eye(4)[None]; vfs[0, :3, 3] = 10.0
        >>> slice_voxel_coordinates(vfs, 3, 1.0)[:, 0, 0, 2].tolist()        # row 0, column 2
        [11.0, 9.0, 10.0]
    """
    m = np.asarray(voxel_from_slice, dtype=np.float64)
    idx = pixel_offsets_mm(size, pixel_mm)
    origin = m[:, :3, 3] + offset_mm * m[:, :3, 2]                                # [B, 3]
    along_x = m[:, None, :3, 0] * idx[None, :, None]                              # [B, L, 3] by column
    along_y = m[:, None, :3, 1] * idx[None, :, None]                              # [B, L, 3] by row
    rows = origin.T[:, :, None, None] + along_y.transpose(2, 0, 1)[:, :, :, None]          # [3, B, L, 1]
    return rows + along_x.transpose(2, 0, 1)[:, :, None, :]


def sample_points(volume: ArrayLike, affine: ArrayLike, points: ArrayLike, order: int = 1) -> NDArray:
    """Interpolate ``volume`` at world points ``[..., 3]`` (zero outside the field of view)."""
    vox = apply(np.linalg.inv(np.asarray(affine, dtype=np.float64)), points)
    coords = np.moveaxis(vox, -1, 0).reshape(3, -1)
    vals = ndimage.map_coordinates(np.asarray(volume, dtype=np.float32), coords, order=order,
                                   mode="constant", cval=0.0, prefilter=False)
    return vals.reshape(vox.shape[:-1])


def psf_offsets(thickness_mm: float, step_mm: float) -> tuple[NDArray, NDArray]:
    """Through-plane quadrature: offsets (mm) and normalised Gaussian weights for FWHM = thickness."""
    sigma = thickness_mm * FWHM_TO_SIGMA
    n = max(3, int(np.ceil(4.0 * sigma / max(step_mm, 1e-6))) | 1)
    offsets = np.linspace(-2.0 * sigma, 2.0 * sigma, n)
    w = np.exp(-0.5 * (offsets / sigma) ** 2)
    return offsets, w / w.sum()


def sample_slices(
    volume: ArrayLike,
    affine: ArrayLike,
    poses: ArrayLike,
    size: int,
    pixel_mm: float,
    *,
    thickness_mm: float | None = None,
    inplane_fwhm_mm: float | None = None,
    order: int = 1,
) -> NDArray[np.float32]:
    """Sample ``L x L`` slices ``[B, L, L]`` at ``poses`` ``[B, 4, 4]`` by trilinear interpolation.

    Args:
        volume: ``[I, J, K]`` array.
        affine: voxel -> world (RAS mm) ``4 x 4``.
        poses: slice -> world poses.
        size: ``L``.
        pixel_mm: ``s``.
        thickness_mm: if given, a Gaussian through-plane PSF with this FWHM (thick slices).
        inplane_fwhm_mm: if given, a Gaussian in-plane PSF with this FWHM (default with a
            thickness: ``1.2 * pixel_mm``).
        order: interpolation order (1 = trilinear).
    """
    vfs = np.linalg.inv(np.asarray(affine, dtype=np.float64)) @ np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    vol = np.asarray(volume, dtype=np.float32)

    def plane(offset_mm: float) -> NDArray[np.float32]:
        return ndimage.map_coordinates(vol, slice_voxel_coordinates(vfs, size, pixel_mm, offset_mm), order=order,
                                       mode="constant", cval=0.0, prefilter=False)

    if thickness_mm is None:
        out = plane(0.0)
    else:
        step = 0.5 * float(np.min(np.linalg.norm(np.asarray(affine)[:3, :3], axis=0)))
        offsets, weights = psf_offsets(thickness_mm, step)
        out = np.zeros((len(vfs), size, size))
        for o, w in zip(offsets, weights):          # one plane at a time: memory of one, not of all
            out += w * plane(float(o))
        if inplane_fwhm_mm is None:
            inplane_fwhm_mm = INPLANE_FWHM_FACTOR * pixel_mm
    if inplane_fwhm_mm:
        sigma_px = inplane_fwhm_mm * FWHM_TO_SIGMA / pixel_mm
        out = ndimage.gaussian_filter(out, sigma=(0.0, sigma_px, sigma_px), mode="constant")
    return out.astype(np.float32)


def mask_centroids(masks: ArrayLike, pixel_mm: float, threshold: float = 0.5) -> tuple[NDArray, NDArray]:
    """In-plane centroids ``[B, 2]`` (x, y mm in the slice frame) of slice masks ``[B, L, L]``.

    Returns ``(centroids, counts)``; a slice with an empty mask has centroid ``(0, 0)`` and count 0.
    """
    m = (np.asarray(masks) > threshold).astype(np.float64)
    size = m.shape[-1]
    xy = slice_pixel_coordinates(size, pixel_mm)
    counts = m.sum(axis=(-1, -2))
    sums = np.einsum("brc,rcd->bd", m, xy)
    cent = np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None], 0.0)
    return cent, counts


def recentre(poses: ArrayLike, shift_xy_mm: ArrayLike) -> NDArray[np.float64]:
    """Poses whose slice-frame origin is moved in-plane by ``shift_xy_mm`` ``[B, 2]``.

    ``P' = P o translate(dx, dy, 0)``: the same plane, its centre now at the old frame's
    ``(dx, dy)`` (the crop/centre step, with the label moved along).
    """
    s = np.asarray(shift_xy_mm, dtype=np.float64)
    shift = make_pose(np.broadcast_to(np.eye(3), s.shape[:-1] + (3, 3)),
                      np.concatenate([s, np.zeros(s.shape[:-1] + (1,))], axis=-1))
    return np.asarray(poses, dtype=np.float64) @ shift


def centre_on_mask(
    mask_volume: ArrayLike, affine: ArrayLike, poses: ArrayLike, size: int, pixel_mm: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Re-centre slice poses on the centroid of the mask they cut.

    Returns ``(centred_poses [B, 4, 4], shift_xy_mm [B, 2])``.
    """
    masks = sample_slices(mask_volume, affine, poses, size, pixel_mm)
    cent, _ = mask_centroids(masks, pixel_mm)
    return recentre(poses, cent), cent
