"""Image consistency across stacks: the stage's poses refined where slices of different stacks cross.

After the stack-consistency stage, what is left of a slice's error is mostly the motion its stack
model could not follow and each stack's offset from the others: things the network's poses cannot
show, and the slices' images can (:mod:`service.consistency.intersections`). The stage's poses
``P_k`` (network frame -> atlas) are refined by a right perturbation in each slice's network frame
(its mask centroid, its own axes), ``P_k' = P_k exp(d_k)``, minimising the image term (soft L1)
plus ``sum_k |d_k / s_k|^2``, the stage's expected error as a Gaussian prior, by Levenberg-Marquardt
in passes from coarse to fine in-plane smoothing, the stacks' intensities matched where they cross
from the second pass on (:mod:`~service.consistency.intensity_match`). The images do not see a rigid
move of all slices together: the result is put back in the frame of the stage's poses. Slices on no
line follow their stack's nearest checked slices; each slice's expected error follows its remaining
mismatch and how firmly the images hold it (its Laplace spread at the optimum;
:mod:`~service.consistency.refined_errors`).

Example (the passes' smoothing and point spacing, coarse to fine, mm):
    >>> [(sigma, spacing) for sigma, spacing, _ in PASSES]
    [(4.5, 9.0), (3.0, 3.0), (0.9, 2.0)]
"""

from __future__ import annotations

import copy
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import linalg

from service.consistency.image_jacobian import PointJacobian, image_jacobian
from service.consistency.intensity_match import matched
from service.consistency.intersections import ImageTerm, candidate_pairs
from service.consistency.refined_errors import laplace_spread_mm
from service.consistency.slice_images import BlockedStack, SampledStack, StackImages
from service.geometry import se3
from service.geometry.anchors import ed

ANCHOR_RADIUS_MM = 40.0
"""Rotation errors are weighed as the shift they make this far from a slice's centre."""
COARSE_POINTS = 8_000
"""Points of the coarsest pass at most: it only brings slices within reach of the finer passes."""
PASSES: tuple[tuple[float, float, int | None], ...] = ((4.5, 9.0, COARSE_POINTS), (3.0, 3.0, None), (0.9, 2.0, None))
"""Each pass's in-plane smoothing and spacing of its points along the lines (mm), and its points at
most (None: :data:`~service.consistency.intersections.MAX_POINTS`), coarse to fine. The finest
smoothing is about a 3 mm slice's own profile across its plane (3 / sqrt(12) mm), so that two
crossing thick slices see the same blur (at the true poses of a noise-free phantom the refinement
then hardly moves them). The coarser passes bring slices that moved far within reach of the finer
ones: under jumping and independent motion the 4.5 mm pass, its points two sigmas apart, leaves
fewer slices far off. Smoothing in the plane only, a coarse pass's optimum lies off the truth (the
two slices' 3D blurs differ): a 6 mm pass puts it beyond the finest pass's reach
(docs/reports/consistency-experiments.md)."""
MIN_BRAIN_PIXELS = 20
"""Slices with less brain than this take no part (their lines cross too little brain to tell)."""
MIN_LINE_WEIGHT = 1.0
"""A pair takes part when its line crosses both brains over this many points' worth (mask weights)."""
TOLERANCE = 1e-2
"""A pass ends when an iteration lowers the objective by less than this fraction."""
SMOOTHING_WORKERS = 2
"""Stacks smoothed at a time (threads) before the passes."""
MATCHED_FROM_PASS: int | None = 1
"""The first pass (0: the coarsest) whose images are divided by the stacks' fitted gains and shading
(:func:`~service.consistency.intensity_match.matched`, at the pass's starting poses; None: no pass's).
The coarsest pass moves slices from where the stack stage left them, up to a few millimetres: fitted
there, a stack's gain and slope take up part of the mismatch of a stack placed off as a whole, which
is what moves it back; from the second pass on, the lines show the same tissue."""


@dataclass
class Refinement:
    """What the image term did to a request's poses."""

    poses: list[NDArray[np.float64]]      # per stack [n, 4, 4], network frame -> atlas
    moved_mm: list[NDArray[np.float64]]   # per stack [n]: how far each slice moved (E.D.-like, mm)
    pairs: int                            # intersecting pairs used
    cost_before: float                    # the finest pass's image term per weighted point, at the stage's
                                          # poses / at the refined ones (one smoothing, one set of points;
                                          # the intensities as they are, unmatched: the scale that
                                          # refined_errors.AGREED_MISMATCH judges)
    cost_after: float
    mismatch: list[NDArray[np.float64]]   # per stack [n]: each slice's image term per weighted point, after (NaN: none)
    spread_mm: list[NDArray[np.float64]]  # per stack [n]: each refined slice's Laplace spread (mm; NaN: not refined)


def refine(stacks: list[StackImages], poses: list[NDArray], expected_error_mm: list[NDArray], *,
           passes: tuple[tuple[float, float, int | None], ...] = PASSES, noise: float = 0.15,
           prior_weight: float = 1.0, iterations: int = 8,
           smoothed: list[dict[float, SampledStack]] | None = None) -> Refinement:
    """Refine every free slice's pose so that slices of different stacks agree where they cross.

    Args:
        stacks: each stack's images (:class:`StackImages`); a stack marked ``fixed`` takes part as
            a fixed partner: the others are refined against it, and since it holds the frame,
            nothing is put back in the stage's frame.
        poses: each stack's poses ``[n, 4, 4]`` (network frame -> atlas), the stage's output.
        expected_error_mm: each stack's expected E.D. per slice ``[n]`` (the prior's scale; non-finite: 10 mm).
        passes: each pass's in-plane smoothing and spacing of the points along the lines (mm), and its
            points at most (None: :data:`~service.consistency.intersections.MAX_POINTS`), coarse to fine.
        noise: the intensity difference (in units of a stack's median brain intensity) that counts
            as one standard deviation; the soft-L1 loss turns linear beyond it.
        prior_weight: multiplies the prior's residuals (1: the stage's expected errors as they are).
        iterations: Gauss-Newton iterations per pass.
        smoothed: per stack, its smoothed images by sigma: what is there is used (:func:`smooth_ahead`),
            what is missing is made and kept, for a later refinement of the same stacks (a
            request's second step).

    Returns:
        :class:`Refinement`; a request with fewer than two stacks, or no crossing pairs, comes back
        unchanged.
    """
    sizes = [len(p) for p in poses]
    bounds = np.cumsum([0, *sizes])
    unchanged = Refinement([p.copy() for p in poses], [np.zeros(n) for n in sizes], 0, np.nan, np.nan,
                           [np.full(n, np.nan) for n in sizes], [np.full(n, np.nan) for n in sizes])
    if len(stacks) < 2:
        return unchanged
    stack_of = np.repeat(np.arange(len(stacks)), sizes)
    local = np.concatenate([np.arange(n) for n in sizes])
    p0 = np.concatenate(poses)
    network_from_slice = se3.inverse(np.concatenate([s.slice_from_network for s in stacks]))
    pixels = np.concatenate([s.masks.reshape(len(s.masks), -1).sum(axis=1) for s in stacks])
    taking_part = (pixels >= MIN_BRAIN_PIXELS) & np.concatenate([s.active for s in stacks])
    anchored = taking_part & np.repeat([s.fixed for s in stacks], sizes)
    free = taking_part & ~anchored
    if not free.any():
        return unchanged
    col = -np.ones(len(p0), int)
    col[free] = np.arange(free.sum())
    sd = np.concatenate([np.where(np.isfinite(e), e, 10.0) for e in expected_error_mm])
    prior = _prior_sd(np.maximum(sd[free], 0.5)) / prior_weight            # [F, 6]
    radius = max(_brain_radius(s) for s in stacks)
    x = np.zeros((int(free.sum()), 6))

    def poses_at(params: NDArray) -> NDArray:
        twist = np.zeros((len(p0), 6))
        twist[free] = params
        return p0 @ se3.exp(twist)

    def atlas_from_slice(params: NDArray) -> NDArray:
        return poses_at(params) @ network_from_slice

    pairs = candidate_pairs(atlas_from_slice(x), stack_of, taking_part)
    pairs = pairs[free[pairs[:, 0]] | free[pairs[:, 1]]]                    # not two fixed partners
    if not len(pairs):
        return unchanged
    finest = None                         # the last pass's points on its unmatched images, and their weights
    used = 0
    mismatch = np.full(len(p0), np.nan)
    smoothed_passes = _smoothed_passes(stacks, [p[0] for p in passes], smoothed)
    for index, ((_, step, budget), sampled) in enumerate(zip(passes, smoothed_passes)):
        t = np.arange(-radius, radius + 1e-9, step)
        start = atlas_from_slice(x)
        term = ImageTerm(sampled, stack_of, local, pairs, t, start)
        term.select_in_masks(start, MIN_LINE_WEIGHT, budget)
        if not len(term.pair_of):
            break
        plain = term                      # the same points on the images as they are
        if MATCHED_FROM_PASS is not None and index >= MATCHED_FROM_PASS:
            plain = copy.copy(term)
            sampled, _ = matched(sampled, term, start, stack_of)
            term.use_images(sampled)
        used = len(term.pairs)

        def residual(params: NDArray, term: ImageTerm = term) -> NDArray:
            return term.residuals(atlas_from_slice(params)) / noise

        def jac(params: NDArray, term: ImageTerm = term) -> PointJacobian:
            current = poses_at(params)
            return image_jacobian(term, current @ network_from_slice, current, col, noise)

        x, r = _gauss_newton(residual, jac, x, prior, iterations, residual(x))
        finest = (plain, term.sw)
        mismatch = _per_slice(r, term.sw, term.pairs[term.pair_of], len(p0))
    final = atlas_from_slice(x) @ se3.inverse(network_from_slice)
    checked = np.isfinite(mismatch)
    if not checked.any():
        return unchanged
    spread = np.full(len(p0), np.nan)
    spread[free] = laplace_spread_mm(_normal_equations(jac(x), x, r, prior)[0])   # the last pass, at its optimum
    final = follow_neighbours(final, p0, checked, stack_of, local)
    if not anchored.any():
        # The images do not see the request's frame; it goes back where the stage's poses put it.
        frame = se3.frechet_mean(p0[checked] @ se3.inverse(final[checked]), 1.0 / np.maximum(sd[checked], 0.5) ** 2)
        final = frame @ final
    moved = ed(final, p0)
    cut = lambda a: [a[i:j] for i, j in zip(bounds[:-1], bounds[1:])]  # noqa: E731
    plain, sw = finest                    # the same points and smoothing, the intensities as they are
    before, after = (_mean_square(plain.residuals(atlas_from_slice(at)) / noise, sw) for at in (np.zeros_like(x), x))
    return Refinement(cut(final), cut(moved), used, before, after, cut(mismatch), cut(spread))


def smooth_ahead(stacks: list[StackImages], passes: tuple[tuple[float, float, int | None], ...] = PASSES,
                 ) -> list[dict[float, SampledStack]]:
    """Every pass's smoothed images of ``stacks`` (per stack, by sigma): :func:`refine`'s
    ``smoothed``, made before it runs. They depend on the slices' images and masks alone, not on
    their poses or on which slices take part, so a caller can make them while the poses are still
    being worked out (the request's stack stage leaves most of a core idle)."""
    store: list[dict[float, SampledStack]] = [{} for _ in stacks]
    for _ in _smoothed_passes(stacks, [p[0] for p in passes], store):
        pass
    return store


def _smoothed_passes(stacks: list[StackImages], sigmas_mm: list[float],
                     kept: list[dict[float, SampledStack]] | None = None) -> Iterator[list[SampledStack]]:
    """The stacks smoothed by each of ``sigmas_mm`` in turn, :data:`SMOOTHING_WORKERS` stacks at a
    time (the filters release the GIL). One pass's images at a time are kept; with ``kept`` (per
    stack, its smoothed images by sigma) all of them, and what is there already is not made again."""
    store = kept if kept is not None else [{} for _ in stacks]
    with ThreadPoolExecutor(max_workers=SMOOTHING_WORKERS) as pool:
        missing = [i for i, k in enumerate(store) if any(sigma not in k for sigma in sigmas_mm)]
        blocked = dict(zip(missing, pool.map(BlockedStack.of, [stacks[i] for i in missing])))
        for sigma in sigmas_mm:
            new = [i for i, k in enumerate(store) if sigma not in k]
            for i, made in zip(new, pool.map(lambda i: SampledStack(stacks[i], sigma, blocked[i]), new)):
                store[i][sigma] = made
            yield [k[sigma] for k in store]
            if kept is None:
                for k in store:
                    del k[sigma]


def follow_neighbours(final: NDArray, start: NDArray, checked: NDArray, stack_of: NDArray,
                      index: NDArray) -> NDArray[np.float64]:
    """Slices the images could not check (on no line: the edge slices, those left out) move as the
    nearest checked slices of their stack on either side did (the mean of their corrections
    ``final start^-1``): the stage placed them with their stack, and their stack moved.

    Example:
        >>> from service.geometry.pose import translate
        >>> start = np.stack([np.eye(4)] * 3)
        >>> final = np.stack([translate([2.0, 0, 0]), np.eye(4), translate([4.0, 0, 0])])
        >>> follow_neighbours(final, start, np.array([True, False, True]), np.zeros(3, int), np.arange(3))[1, :3, 3].tolist()
        [3.0, 0.0, 0.0]
    """
    out = final.copy()
    correction = final @ se3.inverse(start)
    moved, sides = [], []
    for g in np.flatnonzero(~checked):
        mine = np.flatnonzero(checked & (stack_of == stack_of[g]))
        if not len(mine):
            continue
        below, above = mine[index[mine] < index[g]], mine[index[mine] > index[g]]
        near = [side[np.argmin(np.abs(index[side] - index[g]))] for side in (below, above) if len(side)]
        moved.append(g)
        sides.append(near if len(near) == 2 else near * 2)    # one neighbour: its correction twice
    if moved:                                                 # all the means in one batched call
        out[moved] = se3.frechet_mean(correction[np.array(sides)]) @ start[moved]
    return out


def _gauss_newton(residual, jacobian, x: NDArray, prior: NDArray, iterations: int,  # noqa: ANN001
                  r: NDArray | None = None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Levenberg-Marquardt on the soft-L1 image residuals plus the Gaussian prior ``x / prior``
    (IRLS weights; ``jacobian(x)`` the residuals' :class:`PointJacobian`; ``r`` the residuals at ``x``
    where known). Returns the parameters and their residuals.

    The damped normal matrix is symmetric positive definite (the prior's diagonal alone makes it
    so): it is solved by Cholesky."""

    def cost(r: NDArray, params: NDArray) -> float:
        return float(np.sum(2.0 * (np.sqrt(1.0 + r ** 2) - 1.0)) + np.sum((params / prior) ** 2))

    r = residual(x) if r is None else r
    c = cost(r, x)
    mu = 1e-3
    for _ in range(iterations):
        hess, grad = _normal_equations(jacobian(x), x, r, prior)
        while True:
            step = linalg.cho_solve(linalg.cho_factor(hess + mu * np.diag(np.diag(hess)), check_finite=False),
                                    -grad, check_finite=False)
            trial = x + step.reshape(x.shape)
            r_trial = residual(trial)
            c_trial = cost(r_trial, trial)
            if c_trial < c:
                x, r, mu = trial, r_trial, max(mu / 3.0, 1e-6)
                done = c - c_trial < TOLERANCE * c
                c = c_trial
                break
            mu *= 10.0
            if mu > 1e6:
                return x, r
        if done:
            break
    return x, r


def _normal_equations(jac: PointJacobian, x: NDArray, r: NDArray, prior: NDArray) -> tuple[NDArray, NDArray]:
    """The Gauss-Newton normal matrix and gradient of the objective at ``x``: the soft-L1 image term
    through its IRLS weights ``1 / sqrt(1 + r^2)`` plus the Gaussian prior ``x / prior``."""
    hess, grad = jac.normal(1.0 / np.sqrt(1.0 + r ** 2), r)
    hess[np.diag_indices_from(hess)] += 1.0 / prior.ravel() ** 2
    return hess, grad + (x / prior ** 2).ravel()


def _prior_sd(sd_mm: NDArray) -> NDArray[np.float64]:
    """``[K, 6]`` per-coordinate prior sd of a slice's twist (rotation rad, translation mm) from its
    expected E.D.: the squared error shared out evenly over six coordinates."""
    e = np.asarray(sd_mm, dtype=np.float64)[:, None] / np.sqrt(6.0)
    return np.concatenate([np.repeat(e / ANCHOR_RADIUS_MM, 3, axis=1), np.repeat(e, 3, axis=1)], axis=1)


def _per_slice(r: NDArray, sw: NDArray, point_pairs: NDArray, n: int) -> NDArray[np.float64]:
    """``[n]`` each slice's weighted mean squared image residual over the points of its lines
    (NaN for a slice on no line)."""
    num = np.bincount(point_pairs[:, 0], r ** 2, n) + np.bincount(point_pairs[:, 1], r ** 2, n)
    den = np.bincount(point_pairs[:, 0], sw ** 2, n) + np.bincount(point_pairs[:, 1], sw ** 2, n)
    return np.where(den > 0, num / np.maximum(den, 1e-12), np.nan)


def _mean_square(r: NDArray, sw: NDArray) -> float:
    return float(np.sum(r ** 2) / max(float(np.sum(sw ** 2)), 1e-12))


def _brain_radius(s: StackImages) -> float:
    """The largest distance (mm) of a brain pixel from its slice's network origin, over the stack.

    Along a row, the farthest brain pixel from any point is the row's first or last one, so only
    those two per row and slice are measured."""
    masks = np.asarray(s.masks, bool)
    rows = masks.any(axis=2)                                                  # [n, H]
    if not rows.any():
        return 0.0
    h, w = masks.shape[1:]
    first = np.argmax(masks, axis=2)
    last = w - 1 - np.argmax(masks[:, :, ::-1], axis=2)
    y = (np.arange(h) - (h - 1) / 2.0) * s.pixel_mm[0] - s.slice_from_network[:, 1, 3][:, None]
    ends = np.stack([first, last])                                            # [2, n, H]
    x = (ends - (w - 1) / 2.0) * s.pixel_mm[1] - s.slice_from_network[:, 0, 3][None, :, None]
    return float(np.sqrt(x ** 2 + y[None] ** 2)[:, rows].max())
