"""N4 bias-field estimation (Tustison et al., IEEE TMI 2010) in numpy, for the small fit images of
:mod:`service.preprocess.bias`.

The service fits the bias field on an image shrunk to pixels of 8 mm or more (a few thousand
voxels). On such an image ITK's filter spends its time on fixed work per iteration, not on the
voxels, and N4 takes dozens of iterations to converge; the same algorithm written as small dense
contractions costs a fraction of that (docs/reports/benchmark-history.md). Each iteration, as in ITK's
``N4BiasFieldCorrectionImageFilter``:

1. the log image less the current log field is sharpened: its histogram (200 bins, triangular
   Parzen windows) is deconvolved by a Gaussian (FWHM 0.15 in log intensity, Wiener noise 0.01),
   and each value is mapped to its expected true value ``E[u | v]``;
2. the residual (the values less their sharpened values) is approximated by a cubic B-spline on
   the current control lattice with the single-level multilevel B-spline approximation of Lee,
   Wolberg and Shin (1997), whose lattice is added to the field's;
3. the iterations of a level stop when the coefficient of variation of ``exp`` of the field's change
   over the mask falls under the convergence threshold; each level doubles the lattice's mesh.

The field lives on the image's index domain (spacing and direction do not enter, as in ITK's fit).

Example:
    >>> import numpy as np
    >>> x, y, z = np.meshgrid(*(np.linspace(-1, 1, n) for n in (12, 14, 6)), indexing="ij")
    >>> tissue = np.where(np.hypot(x, y) < 0.5, 100.0, 60.0)
    >>> field = n4_log_field(tissue * np.exp(0.3 * x), np.ones(tissue.shape, bool))
    >>> bool(np.corrcoef(field.ravel(), 0.3 * x.ravel())[0, 1] > 0.95)
    True
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

SPLINE_ORDER = 3
BINS = 200
FWHM = 0.15
WIENER_NOISE = 0.01
CONVERGENCE = 0.001


def _basis(u: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """The first control point and the 4 cubic B-spline weights ``[n, 4]`` at parametric ``u``."""
    span = np.floor(u).astype(np.intp)
    t = u - span
    weights = np.stack([(1 - t) ** 3, 3 * t ** 3 - 6 * t ** 2 + 4, -3 * t ** 3 + 3 * t ** 2 + 3 * t + 1, t ** 3], -1) / 6
    return span, weights


def _parametric(index: NDArray, size: int, elements: int) -> NDArray[np.float64]:
    """Voxel indices -> B-spline parameter in ``[0, elements)`` (the far end kept inside its span)."""
    if size < 2:
        return np.zeros(len(index))
    u = np.asarray(index, np.float64) * elements / (size - 1)
    return np.minimum(u, elements * (1 - 1e-9))


def _contract(grid: NDArray[np.float64], matrices: list[NDArray[np.float64]], axis: int) -> NDArray[np.float64]:
    """``grid`` contracted with one matrix per axis, over each matrix's ``axis`` (0: grid -> lattice,
    1: lattice -> grid); three small tensor products instead of one 6-index sum."""
    for m in matrices:
        grid = np.tensordot(grid, m, (0, axis))
    return grid


class _Lattice:
    """A level's cubic B-spline lattice over the whole image, as one basis matrix ``[n_d, size]`` per
    axis: the tensor-product weights of a voxel are the products of its rows, so fitting and
    evaluating are dense contractions over the grid (the mask enters as a 0/1 array)."""

    def __init__(self, shape: tuple[int, ...], mask: NDArray[np.bool_], elements: int) -> None:
        self.size = elements + SPLINE_ORDER
        self.axes = []
        for n in shape:
            span, w = _basis(_parametric(np.arange(n), n, elements))
            m = np.zeros((n, self.size))
            np.put_along_axis(m, span[:, None] + np.arange(SPLINE_ORDER + 1), w, axis=1)
            self.axes.append(m)
        self.cubes = [m ** 3 for m in self.axes]
        # A voxel's sum of squared weights over its 64 control points is the product of its rows' sums.
        norms = [np.square(m).sum(axis=1) for m in self.axes]
        self.inverse_norm = 1.0 / np.einsum("i,j,k->ijk", *norms)
        self.denominator = _contract(mask.astype(np.float64), [np.square(m) for m in self.axes], 0)

    def fit(self, residual: NDArray[np.float64]) -> NDArray[np.float64]:
        """The lattice that approximates ``residual`` (0 outside the mask) by the single-level MBA:
        each control point takes the ``w^2``-weighted mean of the points' own solutions
        ``w z / sum(w^2)``, i.e. ``sum(w^3 z / sum(w^2)) / sum(w^2)``."""
        numerator = _contract(residual * self.inverse_norm, self.cubes, 0)
        return np.divide(numerator, self.denominator, out=np.zeros_like(numerator), where=self.denominator > 0)

    def on_grid(self, lattice: NDArray[np.float64]) -> NDArray[np.float64]:
        return _contract(lattice, self.axes, 1)


def sharpen(values: NDArray[np.float64], bins: int = BINS, fwhm: float = FWHM,
            noise: float = WIENER_NOISE) -> NDArray[np.float64]:
    """Each value's expected true value ``E[u | v]`` once its histogram is deconvolved by a Gaussian
    of ``fwhm`` (Wiener filter of ``noise``)."""
    lo, hi = float(values.min()), float(values.max())
    slope = (hi - lo) / (bins - 1) if hi > lo else 1.0
    c = (values - lo) / slope
    i = np.minimum(np.floor(c).astype(np.intp), bins - 2)       # the top value: bin bins-2 with weight 0
    f = c - i
    hist = np.bincount(i, 1 - f, bins) + np.bincount(i + 1, f, bins)
    padded = 2 ** (int(np.ceil(np.log2(bins))) + 1)
    offset = (padded - bins) // 2
    v = np.zeros(padded)
    v[offset:offset + bins] = hist
    scaled = fwhm / slope
    n = np.minimum(np.arange(padded), padded - np.arange(padded))
    gauss = 2 * np.sqrt(np.log(2) / np.pi) / scaled * np.exp(-4 * np.log(2) * n.astype(np.float64) ** 2 / scaled ** 2)
    ff = np.fft.fft(gauss)
    wiener = (np.conj(ff) / (np.conj(ff) * ff + noise)).real
    u = np.maximum(np.fft.ifft(np.fft.fft(v) * wiener).real, 0.0)
    centres = lo + (np.arange(padded) - offset) * slope
    numerator = np.fft.ifft(np.fft.fft(centres * u) * ff).real
    denominator = np.fft.ifft(np.fft.fft(u) * ff).real
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.nan_to_num(numerator / denominator, nan=0.0, posinf=0.0, neginf=0.0)[offset:offset + bins]
    return e[i] + (e[i + 1] - e[i]) * f


def n4_log_field(image: NDArray, mask: NDArray, iterations: tuple[int, ...] = (50, 50), control_points: int = 4,
                 threshold: float = CONVERGENCE) -> NDArray[np.float64]:
    """The log bias field of ``image`` (3D, positive inside ``mask``) on its whole grid.

    Args:
        image: intensities; only those inside ``mask`` (positive and finite) are fitted.
        mask: the voxels the fit uses.
        iterations: the most iterations per fitting level; one level per entry.
        control_points: control points per axis at the first level (the mesh doubles per level).
        threshold: a level ends when the field's change has a coefficient of variation under this.
    """
    image = np.asarray(image, np.float64)
    mask = np.asarray(mask, bool) & (image > 0) & np.isfinite(image)
    field = np.zeros(image.shape)
    if mask.sum() < 2:
        return field
    log_image = np.log(np.where(mask, image, 1.0))
    for level, most in enumerate(iterations):
        lattice = _Lattice(image.shape, mask, (control_points - SPLINE_ORDER) * 2 ** level)
        for _ in range(most):
            uncorrected = (log_image - field)[mask]
            residual = np.zeros(image.shape)
            residual[mask] = uncorrected - sharpen(uncorrected)
            step = lattice.on_grid(lattice.fit(residual))
            field += step
            change = np.exp(-step[mask])
            if change.std(ddof=1) / change.mean() <= threshold:
                break
    return field
