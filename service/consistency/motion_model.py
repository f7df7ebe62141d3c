"""The motion of one stack over acquisition time: a Gaussian process on the slices' rigid proposals.

Every slice ``k`` proposes the stack's ``atlas_from_scanner`` ``S_k = P_k N_k`` (see
:mod:`service.consistency.stack_fit`). Linearised at the rigid fit ``S`` about the stack's centre,
each proposal is a 6-vector ``y_k``: the rotation vector of ``S^-1 S_k`` scaled to mm at the anchor
radius (:data:`~service.geometry.anchors.ANCHOR_HALF_SIZE_MM`) and the translation of the centre
(mm). The fetus moves smoothly over acquisition time; the network errs per slice with a known
spread, and alike on slices next to each other in space (they look alike), so

    ``y_k = f(t_k) + e_k``, ``f ~ GP(0, a^2 exp(-(t - t')^2 / 2 l^2))``,
    ``cov(e_j, e_k) = g^2 s_j s_k / 3 * (r exp(-(j - k)^2 / 2 * 1.5^2) + (1 - r) [j = k])``

per component (times the component's factor of the network's error shape, when the model has
one: :mod:`service.consistency.error_shape`; the errors are then independent in each slice's own
coordinates, where a tilt and a shift of the stack's centre are one error:
:mod:`service.consistency.motion_blocks`), with ``s_k`` the slice's expected E.D. (its calibrated MC spread: it tracks the
network's real error closely, far from the brain's centre most of all) and ``t`` the acquisition
time under one of the candidate orders. The order, the length ``l`` (in acquisitions; ``inf`` is a
rigid stack), the amplitude ``a``, the noise scale ``g`` and the error correlation ``r`` are chosen
by the marginal likelihood over one grid, all candidates at once. The posterior mean is each slice's pose (its own proposal
weighed against its neighbours': the fusion needs no separate step); the closed-form leave-one-out
mean is the pose the other slices predict for it.

Why the marginal likelihood: it does not chase errors that neighbouring slices share (the error
correlation ``r`` explains them), and the slices the network cannot place (a stack's outer planes)
weigh by their spread instead of like the rest. What the stage achieves is measured in
docs/consistency.md ("Measured").

Example:
    >>> import numpy as np
    >>> from service.geometry import se3
    >>> rng = np.random.default_rng(0)
    >>> s = se3.exp(np.array([0.1, 0.2, -0.1, 3.0, 1.0, -2.0]))
    >>> drift = se3.exp(np.outer(np.linspace(-1, 1, 30), [0.0, 0.05, 0.0, 2.0, 0.0, 0.0]))   # smooth motion
    >>> proposals = s @ drift @ se3.exp(rng.normal(0, 0.02, (30, 6)))
    >>> fit = fit_motion(proposals, s, np.full(30, 2.0), {"sequential": np.arange(30)}, np.zeros(3))
    >>> fit.order, bool(np.isfinite(fit.length))
    ('sequential', True)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.consistency.motion_blocks import decompose, posterior, to_slices
from service.consistency.motion_blocks import nll as block_nll
from service.geometry import se3
from service.geometry.anchors import ANCHOR_HALF_SIZE_MM
from service.geometry.pose import make_pose, translate

LENGTHS = (0.5, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, np.inf)
"""Candidate lengths of the motion kernel, in acquisitions (0.5: jitter from one slice to the next;
``inf``: one rigid offset). The lengths and :data:`AMPLITUDES_MM` step by 1.5x or less, so that the
models averaged lie close enough together; a coarser grid is measurably worse, a finer one gains
nothing (measured in docs/reports/consistency-experiments.md)."""
AMPLITUDES_MM = (1.0, 2.0, 3.0, 4.5, 6.0, 9.0, 12.0, 18.0, 24.0)
"""Candidate motion amplitudes (mm at the anchor radius, per component)."""
NOISE_SCALES = tuple(float(2.0 ** (k / 6)) for k in range(7))
"""Candidate factors on the slices' expected errors (the calibration is made on single slices): 1 to
2 in steps of 2^(1/6) (12 %). The likelihood of a stack's 100-200 coordinates is sharp in this
factor, so the average over the models stays near the grid's nearest point: between factors 1.5 times
apart a stack's every expected error jumped by a third where a file's lossless rewrite moved the
likelihood's peak across their midpoint (docs/reports/consistency-experiments.md)."""
ERROR_CORRELATIONS = (0.0, 0.5, 0.9)
"""Candidate correlations of the network's errors between neighbouring slices (they look alike)."""
ERROR_CORRELATION_SLICES = 1.5
"""How far (in slices, along the normal) the network's errors stay correlated."""
NO_VOTE = np.inf
"""Expected error of a slice that must not vote (empty, degenerate, rejected): it only receives."""
MIN_MODEL_WEIGHT = 1e-2
"""Hyper-parameter combinations with less posterior weight than this are left out of the average."""


@dataclass
class MotionFit:
    """The chosen motion model of one stack.

    Attributes:
        poses: ``[n, 4, 4]`` posterior mean of each slice's ``atlas_from_scanner`` (its own
            proposal included, weighed by its error).
        loo: ``[n, 4, 4]`` what the other slices predict for each (leave-one-out mean).
        order: the acquisition order chosen.
        length: kernel length in acquisitions (``inf``: rigid).
        amplitude_mm: motion amplitude per component (mm).
        noise_scale: factor on the expected errors the likelihood preferred.
        error_correlation: correlation of neighbouring slices' network errors it preferred.
        sd_mm: ``[n]`` posterior spread of each slice's motion (E.D.-like mm; in the slice's own
            coordinates, about its origin, when the lever arm is given).
        model_sd_mm: ``[n]`` spread of the others' prediction of each slice (E.D.-like mm).
        placement: ``4 x 4`` the stack's mean placement: ``rigid`` moved by the posterior motion
            averaged over all its slices (where the stack was over its acquisition; the rigid fit
            itself is a robust centre of the proposals, off that mean when the fetus moved).
        placement_sd_mm: its standard error per coordinate (mm).
        placement_cov: ``[n]`` covariance (mm^2 per coordinate) of each slice's posterior error with
            the placement's error (how much of a slice's error the stack's position carries).
    """

    poses: NDArray[np.float64]
    loo: NDArray[np.float64]
    order: str
    length: float
    amplitude_mm: float
    noise_scale: float
    error_correlation: float
    sd_mm: NDArray[np.float64]
    model_sd_mm: NDArray[np.float64]
    placement: NDArray[np.float64] | None = None
    placement_sd_mm: float = float("nan")
    placement_cov: NDArray[np.float64] | None = None


def to_coordinates(proposals: NDArray, rigid: NDArray, centre: NDArray) -> NDArray[np.float64]:
    """``[n, 6]`` coordinates (mm) of ``proposals [n, 4, 4]`` at ``rigid`` about ``centre`` (scanner mm)."""
    about = translate(centre)
    d = se3.inverse(rigid @ about)[None] @ proposals @ about
    return np.concatenate([se3.so3_log(d[:, :3, :3]) * ANCHOR_HALF_SIZE_MM, d[:, :3, 3]], axis=1)


def from_coordinates(y: NDArray, rigid: NDArray, centre: NDArray) -> NDArray[np.float64]:
    """Inverse of :func:`to_coordinates`."""
    d = make_pose(se3.so3_exp(y[:, :3] / ANCHOR_HALF_SIZE_MM), y[:, 3:])
    return (rigid @ translate(centre))[None] @ d @ translate(-centre)[None]


@dataclass(frozen=True)
class Grid:
    """The hyper-parameters the likelihood chooses among (one value each: a refit)."""

    lengths: tuple[float, ...] = LENGTHS
    amplitudes_mm: tuple[float, ...] = AMPLITUDES_MM
    noise_scales: tuple[float, ...] = NOISE_SCALES
    error_correlations: tuple[float, ...] = ERROR_CORRELATIONS


def _correlations(times: dict[str, NDArray], lengths: tuple[float, ...]) -> tuple[list[tuple[str, float]], NDArray]:
    """``[(order, length)]`` and their correlation matrices ``[c, n, n]``."""
    combos, mats = [], []
    for name, t in times.items():
        dt = np.asarray(t, dtype=np.float64)[:, None] - np.asarray(t, dtype=np.float64)[None]
        for length in lengths:
            if np.isinf(length) and combos and any(np.isinf(c[1]) for c in combos):
                continue                                   # a rigid offset does not depend on the order
            combos.append((name, float(length)))
            mats.append(np.ones(dt.shape) if np.isinf(length) else np.exp(-0.5 * (dt / length) ** 2))
    return combos, np.stack(mats)


def fit_motion(proposals: NDArray, rigid: NDArray, noise_mm: NDArray, times: dict[str, NDArray],
               centre: NDArray, grid: Grid = Grid(), axes: NDArray | None = None,
               noise_shape: NDArray | None = None, lever_mm: NDArray | None = None, memo: dict | None = None) -> MotionFit:
    """Choose and apply the motion model of one stack (see the module docstring).

    The covariance of the voting slices' coordinates is ``a^2 K + g^2 E_r`` (motion plus network
    error). Whitened by ``W_r`` it is ``a^2 W K W^T + g^2 I``: one eigendecomposition per (order,
    length, error correlation) and block of coupled coordinates
    (:mod:`service.consistency.motion_blocks`) gives the likelihood of every amplitude and noise
    scale at once.

    The poses are averaged over the grid, each combination weighed by its marginal likelihood (a
    uniform prior over the grid; combinations under :data:`MIN_MODEL_WEIGHT` left out), and their
    spreads include the combinations' disagreement. The average, unlike the single most likely
    combination, does not jump where two combinations are nearly as likely (a small change of the
    slices' expected errors then moves the poses little). The returned hyper-parameters
    (``order``, ``length``, ...) are those of the most likely combination.

    Args:
        proposals: ``[n, 4, 4]`` each slice's ``atlas_from_scanner`` (on its branch).
        rigid: ``4 x 4`` the robust rigid fit the proposals are linearised at.
        noise_mm: ``[n]`` each proposal's expected E.D.; :data:`NO_VOTE` for slices that must not vote.
        times: candidate acquisition times ``{order: [n]}``.
        centre: the stack's centre in scanner mm (rotations are linearised about it).
        grid: the candidate hyper-parameters (:func:`refit` keeps those of an earlier fit).
        axes: ``3 x 3`` the stack's slice axes (columns: in-plane x, y, normal) in scanner
            coordinates; ``noise_shape`` is given along them.
        noise_shape: ``[6]`` or ``[n, 6]`` (per slice) factors on the network's error variance per
            coordinate along ``axes`` (rotation about x, y, normal; translation along x, y, normal);
            default all 1; about each slice's origin when ``lever_mm`` is given, else about the centre.
        lever_mm: ``[n]`` each slice origin's offset from ``centre`` along the normal (mm): the errors
            are then independent in the slices' own coordinates, where a tilt and an in-plane shift
            of the centre are one error (:mod:`service.consistency.motion_blocks`); default 0.
        memo: a dict kept between fits of one stack: a fit with the same errors, times and grid
            as an earlier one reuses its eigendecompositions (:func:`~service.consistency.motion_blocks.decompose`).
    """
    q = np.eye(3) if axes is None else np.asarray(axes, dtype=np.float64)
    y = to_coordinates(proposals, rigid, centre)
    y = np.concatenate([y[:, :3] @ q, y[:, 3:] @ q], axis=1)                                # along the stack's axes
    z = np.zeros(len(y)) if lever_mm is None else np.asarray(lever_mm, dtype=np.float64) / ANCHOR_HALF_SIZE_MM
    vote = np.isfinite(noise_mm)
    noise = np.asarray(noise_mm, dtype=np.float64)[vote]
    shape = np.broadcast_to(np.ones(6) if noise_shape is None else np.asarray(noise_shape, dtype=np.float64),
                            (len(y), 6))[vote]                                              # [m, 6]
    combos, corr = _correlations(times, grid.lengths)
    cv = corr[:, vote][:, :, vote]                                                          # [c, m, m]
    blocks = decompose(y[vote], noise, shape, z[vote], cv, grid.error_correlations, ERROR_CORRELATION_SLICES, memo)
    amps = np.asarray(grid.amplitudes_mm, dtype=np.float64) ** 2
    scales = np.asarray(grid.noise_scales, dtype=np.float64) ** 2
    nll = block_nll(blocks, amps, scales)                                                   # [c, r, a, g]
    ci, ri, ai, gi = (int(i) for i in np.unravel_index(int(np.argmin(nll)), nll.shape))
    order, length = combos[ci]
    noise_var = shape * noise[:, None] ** 2 / 3.0

    # Bayesian model averaging over the grid: every model of weight >= MIN_MODEL_WEIGHT, the most likely always.
    weight = np.exp(-(nll - nll.min()))
    weight /= weight.sum()
    picked = np.argwhere((weight >= MIN_MODEL_WEIGHT) | (weight == weight.max()))          # [k, 4]: (c, r, a, g)
    cs, rs, ais, gis = picked.T
    p = posterior(blocks, cs, rs, amps[ais], scales[gis], corr[cs][:, :, vote], corr[cs], z, z[vote], noise_var)
    posts, covs, svars = p.mean, p.cov.mean(1), p.slice_var.mean(-1)                       # [k, n, 6], [k, n, n], [k, n]
    loos, loo_vars = posts.copy(), svars.copy()
    loos[:, vote], loo_vars[:, vote] = p.loo, p.loo_var.mean(-1)
    wts = weight[tuple(picked.T)] / weight[tuple(picked.T)].sum()
    post = np.einsum("k,knd->nd", wts, posts)
    loo_y = np.einsum("k,knd->nd", wts, loos)
    d, dl = posts - post[None], loos - loo_y[None]                                          # each model's departure
    post_cov = np.einsum("k,knm->nm", wts, covs) + np.einsum("k,knd,kmd->nm", wts, d, d) / 6.0
    slice_var = np.einsum("k,kn->n", wts, svars + (to_slices(d, z) ** 2).mean(-1))
    loo_var = np.einsum("k,kn->n", wts, loo_vars + (to_slices(dl, z) ** 2).mean(-1))
    post = np.concatenate([post[:, :3] @ q.T, post[:, 3:] @ q.T], axis=1)                   # back to scanner axes
    loo_y = np.concatenate([loo_y[:, :3] @ q.T, loo_y[:, 3:] @ q.T], axis=1)
    placement = from_coordinates(post.mean(axis=0, keepdims=True), rigid, centre)[0]
    return MotionFit(from_coordinates(post, rigid, centre), from_coordinates(loo_y, rigid, centre), order,
                     float(length), float(np.sqrt(amps[ai])), float(grid.noise_scales[gi]),
                     float(grid.error_correlations[ri]), np.sqrt(3.0 * np.maximum(slice_var, 0.0)),
                     np.sqrt(3.0 * np.maximum(loo_var, 0.0)), placement, float(np.sqrt(max(post_cov.mean(), 0.0))),
                     post_cov.mean(axis=1))


def refit(fit: MotionFit, proposals: NDArray, rigid: NDArray, noise_mm: NDArray, times: dict[str, NDArray],
          centre: NDArray, **kwargs: NDArray | None) -> MotionFit:
    """:func:`fit_motion` with the most likely hyper-parameters of ``fit`` alone (other votes, other branches)."""
    grid = Grid((fit.length,), (fit.amplitude_mm,), (fit.noise_scale,), (fit.error_correlation,))
    return fit_motion(proposals, rigid, noise_mm, {fit.order: times[fit.order]}, centre, grid, **kwargs)
