"""How the stack fit (:func:`~service.consistency.stack_fit.fit_stack`) weighs each slice's network pose:
its expected error as the noise scale, Tukey weights on its residual to the stack's fit in units of
that scale, and its vote in the motion model from its residual to the other slices' prediction.

Example (three residuals of 1, 2 and 30 mm, expected errors of 2 mm: the outlier weighs nothing):
    >>> w = robust_weights(np.array([1.0, 2.0, 30.0]), np.full(3, 2.0), np.ones(3, bool))
    >>> (w > 0).tolist()
    [True, True, False]
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.consistency.motion_model import NO_VOTE, MotionFit
from service.geometry import se3

MIN_SCALE_MM = 3.0
"""Floor of the robust residual scale (mm), so a near-perfect stack does not reject its noise."""
MIN_NOISE_MM = 0.01
"""Floor of a pose's expected error (mm), so an exact oracle still has a finite weight."""
MIN_STANDARD_SCALE = 0.5
"""Floor of the robust scale of residuals in units of the slices' expected errors."""


def robust_weights(r: NDArray, sig: NDArray | None, use: NDArray) -> NDArray:
    """Tukey weights of the residuals ``r`` (mm), in units of each slice's expected error ``sig`` when
    known (then with a scale floor of :data:`MIN_STANDARD_SCALE`), zero where not ``use``."""
    if sig is None:
        return se3.tukey_weights(r, robust_scale(r[use])) * use
    u = r / sig
    return se3.tukey_weights(u, max(se3.MAD_SCALE * float(np.median(u[use])), MIN_STANDARD_SCALE)) * use


def votes(r_loo: NDArray, motion: MotionFit, sig: NDArray, use: NDArray) -> NDArray:
    """Each usable slice's expected error, inflated by its Tukey weight on the residual to the
    others' prediction in units of the spread that both errors explain (:data:`NO_VOTE` at zero)."""
    z = r_loo / np.sqrt((motion.noise_scale * sig) ** 2 + motion.model_sd_mm ** 2)
    tk = se3.tukey_weights(z, 1.0) * use
    return np.where(tk > 0, sig / np.sqrt(np.maximum(tk, 1e-12)), NO_VOTE)


def noise_scales(expected_error_mm: ArrayLike, use: NDArray) -> NDArray[np.float64]:
    """Each slice's expected error as the fit's noise scale, floored at :data:`MIN_NOISE_MM`; a slice
    that may not vote has none (an empty slice the network never saw: NaN), so it gets the largest
    of the others', which weighs nothing where it does not vote."""
    e = np.asarray(expected_error_mm, dtype=np.float64)
    known = np.isfinite(e)
    floor = float(e[use & known].max()) if (use & known).any() else MIN_NOISE_MM
    return np.maximum(np.where(known, e, floor), MIN_NOISE_MM)


def precisions(sig: NDArray, use: NDArray) -> NDArray:
    """``1 / sig^2`` normalised to a mean of 1 over the usable slices."""
    prec = 1.0 / sig ** 2
    return prec / prec[use].mean()


def robust_scale(r: NDArray) -> float:
    """Robust scale of non-negative residuals ``r``: ``1.4826 median(r)`` (a standard deviation for
    half-normal residuals), floored at :data:`MIN_SCALE_MM`."""
    if len(r) == 0:
        return MIN_SCALE_MM
    return float(max(se3.MAD_SCALE * np.median(r), MIN_SCALE_MM))

