"""Robust statistics: EM outlier rejection of pixels and slices (Gholipour et al. 2010, Kainz et al. 2015).

Residuals ``r = s - A x`` of all pixels are modelled as a mixture of a zero-mean Gaussian (inliers,
variance ``sigma^2``, proportion ``c``) and a uniform density ``m`` over the residual range
(outliers: motion-corrupted pixels, artefacts, misregistered slices). EM gives every pixel its
posterior inlier probability ``p_k``. A slice's potential is the mean ``p_k`` over its pixels; a slice
whose potential is far below the others (below ``ratio x median``, or more than ``k`` robust
standard deviations below the median, the paper's MAD rule with a floor on the MAD) is excluded.
Slice weights are the potentials relative to the median, clipped to ``[0, 1]``.

Example:
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> r = rng.normal(size=4000); sid = np.repeat(np.arange(20), 200)
    >>> r[sid == 7] = rng.uniform(-30, 30, 200)            # one corrupted slice
    >>> w = robust_weights(r, sid, 20)
    >>> np.flatnonzero(w.excluded).tolist(), round(float(w.sigma), 1)
    ([7], 1.0)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.geometry.se3 import MAD_SCALE

EM_ITERATIONS = 12


@dataclass
class RobustWeights:
    """Output of :func:`robust_weights`.

    Attributes:
        pixel_weight: ``[N]`` posterior inlier probability of each pixel (with the tolerance).
        slice_potential: ``[n]`` mean inlier probability of each slice's pixels (NaN: no pixels).
        slice_weight: ``[n]`` in ``[0, 1]``: potential / median potential, 0 for excluded slices.
        excluded: ``[n]`` bool, slices rejected as outliers.
        sigma: inlier standard deviation.
        inlier_fraction: mixing proportion ``c``.
    """

    pixel_weight: NDArray[np.float32]
    slice_potential: NDArray[np.float64]
    slice_weight: NDArray[np.float64]
    excluded: NDArray[np.bool_]
    sigma: float
    inlier_fraction: float


def em_inliers(residuals: NDArray, iterations: int = EM_ITERATIONS,
               tolerance: float = 1.0) -> tuple[NDArray, float, float]:
    """Fit the Gaussian + uniform mixture to residuals; returns ``(p_inlier [N], sigma, c)``.

    ``tolerance > 1`` widens the inlier Gaussian by that factor in the returned posteriors only
    (after the fit), so that just gross outliers lose weight.
    """
    r = np.asarray(residuals, dtype=np.float64)
    if r.size == 0:
        return np.zeros(0), 1.0, 1.0
    spread = float(r.max() - r.min())
    m = 1.0 / max(spread, 1e-12)
    sigma2 = max((MAD_SCALE * float(np.median(np.abs(r - np.median(r))))) ** 2, 1e-12)
    c = 0.9
    r2 = r * r
    p = np.ones_like(r)
    for _ in range(iterations):
        p = posterior(r, float(np.sqrt(sigma2)), c, m)
        total = float(p.sum())
        if total <= 0:
            break
        sigma2 = max(float(np.dot(p, r2)) / total, 1e-12 * spread**2 + 1e-24)
        c = min(max(total / r.size, 1e-3), 1.0 - 1e-6)
    if tolerance != 1.0:
        p = posterior(r, float(np.sqrt(sigma2)) * tolerance, c, m)
    return p, float(np.sqrt(sigma2)), c


def posterior(residuals: NDArray, sigma: float, c: float, m: float) -> NDArray:
    """Inlier probability of residuals under the mixture ``c N(0, sigma^2) + (1 - c) m``."""
    r = np.asarray(residuals, dtype=np.float64)
    g = c * np.exp(-0.5 * r * r / sigma**2) / np.sqrt(2.0 * np.pi * sigma**2)
    return g / (g + (1.0 - c) * m)


def robust_weights(residuals: NDArray, slice_id: NDArray, n_slices: int, *, ratio: float = 0.5, k: float = 3.0,
                   mad_floor: float = 0.1, candidates: NDArray | None = None,
                   tolerance: float = 1.0) -> RobustWeights:
    """Pixel and slice weights from the residuals of all pixels.

    Args:
        residuals: ``[N]`` ``s - A x``.
        slice_id: ``[N]`` slice of each pixel.
        n_slices: ``n``.
        ratio: exclude slices whose potential is below ``ratio x median``.
        k: ... or more than ``k`` robust standard deviations (``1.4826 MAD``) below the median,
        mad_floor: with the MAD taken as at least ``mad_floor x median`` (consistent slices would
            otherwise make any small deviation an outlier).
        candidates: ``[n]`` bool, the slices to judge (default: those with pixels); the median and
            MAD are taken over them.
        tolerance: the pixel weights are the posteriors with the inlier Gaussian widened by this
            factor, so that only gross outliers lose weight (the slice potentials use the fitted one).

    Returns:
        The :class:`RobustWeights`.
    """
    sid = np.asarray(slice_id)
    r = np.asarray(residuals, dtype=np.float64)
    p, sigma, c = em_inliers(r)
    spread = float(r.max() - r.min()) if r.size else 1.0
    pixel = p if tolerance == 1.0 else posterior(r, sigma * tolerance, c, 1.0 / max(spread, 1e-12))
    count = np.bincount(sid, minlength=n_slices)
    cand = count > 0 if candidates is None else np.asarray(candidates, bool) & (count > 0)
    potential = np.full(n_slices, np.nan)
    potential[count > 0] = (np.bincount(sid, p, n_slices) / np.maximum(count, 1))[count > 0]
    excluded = np.zeros(n_slices, bool)
    weight = np.zeros(n_slices)
    if cand.any():
        vals = potential[cand]
        med = float(np.median(vals))
        mad = max(MAD_SCALE * float(np.median(np.abs(vals - med))), mad_floor * med)
        threshold = max(ratio * med, med - k * mad)
        excluded = cand & (np.nan_to_num(potential, nan=0.0) < threshold)
        weight = np.where(cand & ~excluded, np.clip(np.nan_to_num(potential) / max(med, 1e-12), 0.0, 1.0), 0.0)
    return RobustWeights(pixel.astype(np.float32), potential, weight, excluded, sigma, c)


def ncc_outliers(ncc: NDArray, candidates: NDArray, k: float = 3.0, floor: float = 0.05) -> NDArray[np.bool_]:
    """Slices whose NCC with the volume is far below the others': ``ncc < median - k max(1.4826 MAD, floor)``.

    A slice left at a wrong pose can keep plausible residuals (a smooth region, a low-contrast
    slice) while its correlation with the volume stays poor; this is the slice-level test the EM
    pixel model misses. The median and MAD are taken over ``candidates`` (NaN counts as -1).

    Example:
        >>> ncc_outliers(np.array([0.97, 0.98, 0.96, 0.57, 0.99]), np.ones(5, bool)).tolist()
        [False, False, False, True, False]
    """
    cand = np.asarray(candidates, bool)
    x = np.nan_to_num(np.asarray(ncc, dtype=np.float64), nan=-1.0)
    if not cand.any():
        return np.zeros(len(x), bool)
    med = float(np.median(x[cand]))
    mad = max(MAD_SCALE * float(np.median(np.abs(x[cand] - med))), floor)
    return cand & (x < med - k * mad)
