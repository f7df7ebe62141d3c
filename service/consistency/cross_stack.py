"""The stacks of one request, pooled: one fetus position shared as far as their fits agree.

Every decidable stack ``s`` of a request gives its own placement ``A_s`` (where the stack fit,
:mod:`service.consistency.stack_fit`, puts it on average over its acquisition) with a standard
error ``v_s`` per coordinate (from the posterior of its motion model). The stacks share the scanner
frame: where the fetus did not move between them they estimate one position, and their average is
more precise than any of them (the rigid offset of a stack is most of what is left of its error
after the stage).

Between stacks the fetus may have moved, so the pooling is a random-effects model (DerSimonian and
Laird, 1986), in the stage's coordinates (rotation vectors at the anchor radius and translations,
mm, about the stacks' common centre):

::

    y_s = A_s,   y_s ~ N(mu + b_s, v_s),   b_s ~ N(0, tau^2)      (b_s: where the fetus was in stack s)
    Q = sum_s |y_s - y_fixed|^2 / v_s,  df = 6 (S - 1)            (heterogeneity; E[Q] = df when tau = 0)
    tau^2 = max(0, (Q - df) / (6 (sum w - sum w^2 / sum w)))      (method of moments, w = 1 / v)
    A_s' = mu + tau^2 / (tau^2 + v_s) (y_s - mu)                  (each stack's posterior mean)

Stacks that agree within their errors (``tau = 0``) share one position; a fetus that moved between
stacks by more than the stacks' errors (``tau`` large) leaves each stack (nearly) where its own fit
put it. Each stack's slices then move with their stack: ``P_k' = (A_s' A_s^-1) P_k``.

Example:
    >>> import numpy as np
    >>> from service.geometry import se3
    >>> truth = se3.exp(np.array([0.2, -0.1, 0.3, 4.0, 1.0, -2.0]))
    >>> fits = [se3.exp(np.array([0.02 * s, 0, 0, 0, 0, 0])) @ truth for s in (-1, 0, 1)]
    >>> pooled = pool_stacks(np.stack(fits), np.array([2.0, 2.0, 2.0]), np.zeros((3, 3)))
    >>> pooled.tau_mm, bool(np.allclose(pooled.corrections[1], np.eye(4), atol=1e-3))
    (0.0, True)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.consistency.motion_model import from_coordinates, to_coordinates
from service.geometry import se3

COORDINATES = 6


@dataclass
class PooledStacks:
    """Output of :func:`pool_stacks`.

    Attributes:
        corrections: ``[S, 4, 4]`` what each stack's poses are left-multiplied by (atlas frame).
        sd_mm: ``[S]`` standard error of each stack's pooled position per coordinate (mm).
        tau_mm: the spread of the fetus's position between stacks beyond their errors (mm per
            coordinate; 0: one position).
        kept: ``[S]`` the share of each stack's own position in its pooled one (0: the common one).
    """

    corrections: NDArray[np.float64]
    sd_mm: NDArray[np.float64]
    tau_mm: float
    kept: NDArray[np.float64]


def pool_stacks(atlas_from_scanner: ArrayLike, sd_mm: ArrayLike, centres: ArrayLike) -> PooledStacks:
    """Random-effects pooling of the stacks' placements (module docstring).

    Args:
        atlas_from_scanner: ``[S, 4, 4]`` each stack's placement.
        sd_mm: ``[S]`` their standard errors per coordinate (mm).
        centres: ``[S, 3]`` the stacks' centres (scanner mm): rotations are linearised about their mean.
            (``sd_mm`` were measured about each stack's own centre; for the stacks of one brain, a
            few cm apart at most, the difference is a few per cent of the translation errors.)

    Returns:
        The :class:`PooledStacks` (identity corrections for fewer than two stacks).
    """
    a = np.asarray(atlas_from_scanner, dtype=np.float64)
    v = np.maximum(np.asarray(sd_mm, dtype=np.float64), 1e-6) ** 2
    n = len(a)
    if n < 2:
        return PooledStacks(np.repeat(np.eye(4)[None], n, 0), np.sqrt(v), 0.0, np.ones(n))
    centre = np.asarray(centres, dtype=np.float64).mean(axis=0)
    y = to_coordinates(a, a[0], centre)                                   # [S, 6] mm
    w = 1.0 / v
    fixed = (w[:, None] * y).sum(0) / w.sum()
    q = float((w[:, None] * (y - fixed) ** 2).sum())
    df = COORDINATES * (n - 1)
    tau2 = max(0.0, (q - df) / (COORDINATES * (w.sum() - (w ** 2).sum() / w.sum())))
    wr = 1.0 / (v + tau2)
    mu = (wr[:, None] * y).sum(0) / wr.sum()
    mu_var = 1.0 / wr.sum()
    keep = tau2 / (tau2 + v)                                              # [S] share of a stack's own offset
    post = mu + keep[:, None] * (y - mu)
    post_var = keep * v + (1.0 - keep) ** 2 * mu_var
    corrections = from_coordinates(post, a[0], centre) @ se3.inverse(a)
    return PooledStacks(corrections, np.sqrt(post_var), float(np.sqrt(tau2)), keep)
