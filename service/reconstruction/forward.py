"""The slice acquisition model: forward operator ``A`` (volume -> simulated pixels) and its adjoint.

Each pixel is a weighted average of the volume over a 3D Gaussian point-spread function (PSF)
around its atlas position (Kainz et al. 2015): FWHM = slice thickness along the slice normal,
FWHM = ``INPLANE_FWHM_FACTOR`` x pixel size in-plane. The PSF is factorised exactly (for Gaussians)
into

* an isotropic Gaussian ``G`` of the in-plane width, applied to the whole volume with
  ``scipy.ndimage.gaussian_filter`` (``mode="constant"``: a symmetric matrix, so ``G^T = G``), and
* a 1D Gaussian along each slice's normal with the remaining variance
  ``sigma_t^2 - sigma_in^2``, integrated by ``Q`` quadrature points sampled trilinearly.

So ``A = P G`` with ``P`` the sparse matrix of :func:`~service.reconstruction.grid.interpolation_matrix`
and ``A^T = G P^T``, exactly. ``G`` uses one in-plane width for all slices (the median over slices;
stacks of different in-plane resolution share it).

Example:
    >>> u, w = psf_quadrature(5)
    >>> u.round(2).tolist(), round(float(w.sum()), 6), round(float(np.sum(w * u**2)), 6)   # unit variance
    ([-2.08, -1.04, 0.0, 1.04, 2.08], 1.0, 1.0)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from service.geometry.sampling import FWHM_TO_SIGMA, INPLANE_FWHM_FACTOR
from service.reconstruction.grid import Grid, interpolation_matrix
from service.reconstruction.slices import SliceSet

PSF_SPAN_SIGMAS = 2.0
"""Through-plane quadrature points span +- this many standard deviations."""
BLUR_TRUNCATE = 3.0


def psf_quadrature(n_points: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Through-plane quadrature: offsets in units of sigma ``[Q]`` and normalised Gaussian weights ``[Q]``.

    Gaussian weights at evenly spaced points over +-:data:`PSF_SPAN_SIGMAS`, the points then spread
    so that the weights' variance is exactly 1: a few points of a truncated Gaussian have a variance of
    0.85-0.92, which would model slices 4-8 % thinner than they are (the FWHM the slice thickness)."""
    if n_points <= 1:
        return np.zeros(1), np.ones(1)
    u = np.linspace(-PSF_SPAN_SIGMAS, PSF_SPAN_SIGMAS, n_points)
    w = np.exp(-0.5 * u**2)
    w /= w.sum()
    return u / np.sqrt(np.sum(w * u**2)), w


def inplane_sigma_mm(slices: SliceSet) -> float:
    """Standard deviation (mm) of the in-plane PSF, the median over included slices."""
    pix = slices.pixel_mm[slices.include] if slices.include.any() else slices.pixel_mm
    return float(np.median(pix)) * INPLANE_FWHM_FACTOR * FWHM_TO_SIGMA


def psf_sample_points(slices: SliceSet, atlas_from_voxel: ArrayLike, pixels: NDArray | None, n_points: int,
               blur_sigma_mm: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Atlas positions ``[N, Q, 3]`` of the through-plane quadrature points of pixels, and weights ``[Q]``.

    Args:
        slices: the slice set.
        atlas_from_voxel: ``[n, 4, 4]`` current slice transforms.
        pixels: index array of the pixels (``None``: all).
        n_points: ``Q`` (1: no through-plane PSF beyond ``blur_sigma_mm``).
        blur_sigma_mm: the part of the PSF already applied isotropically to the volume.
    """
    u, w = psf_quadrature(n_points)
    t = np.asarray(atlas_from_voxel, dtype=np.float64)
    sid = slices.slice_id if pixels is None else slices.slice_id[pixels]
    pos = slices.positions(t, pixels)
    sigma_t = slices.thickness_mm * FWHM_TO_SIGMA
    rest = np.sqrt(np.maximum(sigma_t**2 - blur_sigma_mm**2, 0.0))            # [n]
    step = slices.normals(t) * rest[:, None]                                 # [n, 3] mm per sigma unit
    return pos[:, None, :] + u[None, :, None] * step[sid][:, None, :], w


class ForwardModel:
    """``A = P G``: the simulated value of every selected pixel from a volume on ``grid``.

    Args:
        slices: the slice set.
        atlas_from_voxel: ``[n, 4, 4]`` slice transforms to simulate with.
        grid: the volume's grid.
        psf_points: ``Q`` through-plane quadrature points (3-5 are enough).
        pixels: index array of the pixels to model (default: all).
        dtype: value type of the operator (float32 in the pipeline, float64 for exact tests).
    """

    def __init__(self, slices: SliceSet, atlas_from_voxel: ArrayLike, grid: Grid, *, psf_points: int = 5,
                 pixels: NDArray | None = None, dtype: type = np.float32) -> None:
        self.grid = grid
        self.dtype = dtype
        self.pixels = pixels
        self.blur_sigma_mm = inplane_sigma_mm(slices)
        self.blur_sigma_vox = self.blur_sigma_mm / grid.spacing
        pts, w = psf_sample_points(slices, atlas_from_voxel, pixels, psf_points, self.blur_sigma_mm)
        self.matrix = interpolation_matrix(grid.voxel_of(pts), grid.shape, w, dtype=dtype)

    @property
    def n_rows(self) -> int:
        """Number of modelled pixels."""
        return self.matrix.shape[0]

    def blur(self, volume: NDArray) -> NDArray:
        """The isotropic in-plane part ``G`` of the PSF (self-adjoint)."""
        x = np.asarray(volume, dtype=self.dtype)
        if np.all(self.blur_sigma_vox < 0.05):
            return x.copy()
        return ndimage.gaussian_filter(x, self.blur_sigma_vox, mode="constant", truncate=BLUR_TRUNCATE)

    def forward(self, volume: NDArray) -> NDArray:
        """``A x``: simulated pixel values ``[N]`` of a volume ``[I, J, K]``."""
        return self.matrix @ self.blur(volume).ravel()

    def adjoint(self, values: NDArray) -> NDArray:
        """``A^T y``: a volume ``[I, J, K]`` from pixel values ``[N]`` (PSF-weighted splatting)."""
        y = np.asarray(values, dtype=self.dtype)
        return self.blur((self.matrix.T @ y).reshape(self.grid.shape))
