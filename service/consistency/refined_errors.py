"""Each slice's expected error after the image refinement (:mod:`~service.consistency.image_refinement`):
what its remaining mismatch and the firmness with which the images hold it say about how well it is
placed, and whether the refinement brought the request's slices into agreement at all.

Example:
    >>> relative = relative_mismatch([np.array([1.0, 4.0, np.nan])])             # over the median, 2.5
    >>> [e.round(2).tolist() for e in expected_after([np.array([4.0, 4.0, 4.0])], relative)]
    [[1.04, 4.16, 7.6]]
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import linalg
from scipy.linalg import lapack

from service.geometry.anchors import twist_spread_mm

REFINED_GAIN = 0.65
"""A refined slice's expected E.D. from the stage's: this times the stage's, times its remaining
mismatch over the request's median to the :data:`MISMATCH_POWER` (:func:`expected_after`; fitted on
simulated moderate acquisitions, docs/consistency.md)."""
MISMATCH_POWER = 1.0
"""How the stage's estimate of a refined slice follows the slice's remaining mismatch (relative to the
request's median): in proportion. A slice the images pin down after motion the stage could not
model (a jump) then loses the stage's over-estimate, and one they still disagree with keeps it: at
the same share of slices over 10 mm accepted, the accept flags keep more of the good slices than
with the square root (docs/reports/accuracy-analyses.md, "Accept flags: earlier calibrations")."""
MAX_RELATIVE_MISMATCH = 8.0
"""The remaining mismatch over the request's median beyond which a slice's stage estimate grows no
further (:func:`expected_after`). Past it the slice is simply lost: on simulated acquisitions its
E.D. no longer grows with the mismatch (docs/reports/consistency-experiments.md), and an estimate in proportion
over-states a few such slices several times over, enough to set the RMS of a request's expected
errors. Such slices are far over any accept limit either way."""
SPREAD_GAIN = 2.0
"""A refined slice's expected E.D. from the images: this times its Laplace spread
(:func:`laplace_spread_mm`). The spread understates the error (neighbouring points of a line are
correlated, the noise scale is nominal): RMS E.D. / RMS spread is 1.9-2.4 on simulated acquisitions
(docs/consistency.md)."""
AGREED_MISMATCH = 1.5
"""The image term per weighted point (the squared intensity difference in units of ``noise``) at or
under which a refinement has brought its slices into agreement where they cross. Above it the slices
still disagree after the refinement, and the stage's expected errors stand: each slice's remaining
mismatch over the request's median then ranks the slices but no longer says how well they are
placed (a run of slices whose brain lost its signal bends its stack-mates beyond what the images
can bring back; docs/reports/consistency-experiments.md)."""
UNCHECKED_GAIN = 1.9
"""A slice on no line (the brain's caps): this times the stage's expected E.D. (the stage
under-states them, and the rest of their stack moved)."""


def relative_mismatch(mismatch: list[NDArray]) -> list[NDArray[np.float64]]:
    """Each slice's remaining image mismatch over the request's median (NaN: on no line, or no slice
    of the request on one).

    Example:
        >>> [m.tolist() for m in relative_mismatch([np.array([1.0, 4.0, np.nan]), np.array([2.0])])]
        [[0.5, 2.0, nan], [1.0]]
    """
    every = np.concatenate(mismatch) if mismatch else np.zeros(0)
    ref = float(np.nanmedian(every)) if np.isfinite(every).any() else np.nan
    return [np.maximum(np.asarray(m, np.float64), 0.0) / max(ref, 1e-12) if np.isfinite(ref)
            else np.full(len(m), np.nan) for m in mismatch]


def agreed(mismatch_after: float) -> bool:
    """Whether a refinement whose image term per weighted point ended at ``mismatch_after`` brought
    its slices into agreement (:data:`AGREED_MISMATCH`; NaN: no points, nothing agreed).

    Example:
        >>> agreed(0.2), agreed(2.4), agreed(float("nan"))
        (True, False, False)
    """
    return bool(mismatch_after <= AGREED_MISMATCH)


def expected_after(expected_error_mm: list[NDArray], relative: list[NDArray],
                   spread_mm: list[NDArray] | None = None) -> list[NDArray[np.float64]]:
    """Each slice's expected E.D. after :func:`~service.consistency.image_refinement.refine`.

    Two estimates meet: the stage's expected error, scaled by the slice's remaining image mismatch
    over the request's median (``relative``, :func:`relative_mismatch`, at most
    :data:`MAX_RELATIVE_MISMATCH`; :data:`REFINED_GAIN`, :data:`MISMATCH_POWER`), and
    what the images themselves allow, :data:`SPREAD_GAIN` times the slice's Laplace spread
    (``spread_mm``, :class:`~service.consistency.image_refinement.Refinement`). The first knows how
    far the stage was off and how well the images agree now, the second how firmly the images hold
    the slice where it is; their geometric mean ranks and scales the errors better than either
    (docs/reports/consistency-experiments.md). A slice without a
    spread keeps the first; a slice on no line gets :data:`UNCHECKED_GAIN` times the stage's.

    Example:
        >>> [e.round(2).tolist() for e in expected_after([np.array([4.0, 4.0, 4.0])], [np.array([0.25, 1.0, np.nan])])]
        [[0.65, 2.6, 7.6]]
        >>> [e.round(2).tolist() for e in expected_after([np.array([4.0])], [np.array([1.0])], [np.array([0.65])])]
        [[1.84]]
        >>> [e.round(2).tolist() for e in expected_after([np.array([4.0, 4.0])], [np.array([8.0, 40.0])])]   # lost alike
        [[20.8, 20.8]]
    """
    spread_mm = spread_mm or [np.full(len(e), np.nan) for e in expected_error_mm]
    out = []
    for e, m, s in zip(expected_error_mm, relative, spread_mm):
        e = np.asarray(e, np.float64)
        stage = np.where(np.isfinite(m), REFINED_GAIN * e * np.minimum(m, MAX_RELATIVE_MISMATCH) ** MISMATCH_POWER,
                         UNCHECKED_GAIN * e)
        images = np.isfinite(m) & np.isfinite(s)
        out.append(np.where(images, np.sqrt(stage * SPREAD_GAIN * np.where(images, s, 1.0)), stage))
    return out


def laplace_spread_mm(hess: NDArray) -> NDArray[np.float64]:
    """``[F]`` each free slice's spread (mm, on the E.D.'s scale) under the Laplace approximation of the
    refinement at its optimum: the ``6 x 6`` diagonal blocks of the inverse of the Gauss-Newton
    Hessian ``hess [6F, 6F]`` (image term and prior) as anchor-point displacements
    (:func:`~service.geometry.anchors.twist_spread_mm`).

    Example (one slice held to 1 mm^2 per translation, 1e-4 rad^2 per rotation: sqrt(3 + 0.96) mm):
        >>> round(float(laplace_spread_mm(np.diag([1e4, 1e4, 1e4, 1.0, 1.0, 1.0]))[0]), 2)
        1.99
    """
    f = len(hess) // 6
    factor, _ = linalg.cho_factor(hess, lower=False, check_finite=False)
    upper, _ = lapack.dpotri(factor, lower=0)                                # the inverse's upper triangle
    blocks = np.triu(upper.reshape(f, 6, f, 6)[np.arange(f), :, np.arange(f), :])
    return twist_spread_mm(blocks + np.swapaxes(np.triu(blocks, 1), 1, 2))
