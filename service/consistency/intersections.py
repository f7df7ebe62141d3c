"""Image consistency across stacks: slices of different stacks must agree where they intersect.

Two slices of differently oriented stacks cut the brain along a common line. At their true poses
both images show the same tissue there; at wrong poses they show different tissue. That is
information no pose regression has (Kim et al., IEEE TMI 2010, "Intersection based motion
correction of multislice MRI"), and it is what tells the stage's remaining error apart: the
motion the stage could not model, and each stack's offset from the others.

The stage's poses ``P_k`` (network frame -> atlas) are refined by a right perturbation in each
slice's network frame (its mask centroid, its own axes), ``P_k' = P_k exp(d_k)``, minimising

::

    sum over pairs (a, b) of slices of different stacks, points x_i on their intersection line:
        w_i (I_a(x_i) - I_b(x_i))^2 / sigma^2                       (robust: soft L1)
    + sum_k |d_k / s_k|^2                                          (the stage's expected error as a prior)

``I_a`` is slice ``a``'s image (bias-corrected, scaled by its stack's median brain intensity,
smoothed in-plane), sampled bilinearly; ``w_i`` the product of both slices' brain masks at ``x_i``,
fixed within a pass and recomputed between passes (a weight that followed the poses would reward
moving the intersections out of the brain). Passes run coarse to fine (in-plane smoothing). The
objective does not see a rigid move of all slices together: the prior keeps the request's frame
where the network put it.

Example:
    >>> import numpy as np
    >>> from service.geometry.pose import make_pose
    >>> axial = make_pose(np.eye(3), [0.0, 0.0, 5.0])                  # the plane z = 5
    >>> coronal = make_pose(se3.so3_exp([np.pi / 2, 0.0, 0.0]), [0.0, 2.0, 0.0])   # the plane y = 2
    >>> pair_points(axial[None], coronal[None], np.array([[0, 0]]), np.array([-10.0, 0.0, 10.0])).round(6).tolist()
    [[[-10.0, 2.0, 5.0], [0.0, 2.0, 5.0], [10.0, 2.0, 5.0]]]
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage, sparse

from service.geometry import se3
from service.geometry.anchors import ed

ANCHOR_RADIUS_MM = 40.0
"""Rotation errors are weighed as the shift they make this far from a slice's centre."""
SIGMAS_MM = (3.0, 0.9)
"""In-plane smoothing of the passes: coarse, then about a 3 mm slice's own profile across its plane
(3 / sqrt(12) mm), so that two crossing thick slices see the same blur (at the true poses of a
noise-free phantom the refinement then moves slices by 0.10 mm, against 0.30 mm at 1.5 mm)."""
REFINED_GAIN = 0.65
UNCHECKED_GAIN = 1.9
"""Expected E.D. after the refinement (:func:`expected_after`), measured on simulated moderate
acquisitions (model 2.11.0, seed 1; seed 2 gave 0.67 and 1.91): a refined slice's error is
``REFINED_GAIN`` times the stage's expected error, scaled by its relative mismatch; a slice the
images could not check (on no line) is ``UNCHECKED_GAIN`` times it (the edge slices: the stage
under-states them, and the rest of their stack moved)."""
MIN_BRAIN_PIXELS = 20
MIN_LINE_WEIGHT = 1.0
TOLERANCE = 1e-3
MAX_POINTS = 60_000
"""Points per pass at most: with many stacks, a fixed random share of the crossing pairs (their
lines whole) bounds the time; three stacks of a fetal brain use about 20,000-50,000."""
"""A pass ends when an iteration lowers the objective by less than this fraction."""
"""A pair takes part when its line crosses both brains over this many points' worth (mask weights)."""
"""Slices with less brain than this take no part (their lines cross too little brain to tell)."""
MIN_SINE = np.sin(np.radians(30.0))
"""Pairs whose planes meet at less than this angle are left out (their line is ill-placed)."""


@dataclass
class StackImages:
    """One stack's slices as the image term needs them.

    Attributes:
        images: ``[n, H, W]`` slice images (any positive scale: each stack is scaled by its median
            brain intensity here).
        masks: ``[n, H, W]`` brain masks.
        pixel_mm: ``(row_mm, col_mm)``.
        slice_from_network: ``[n, 4, 4]`` network frame -> the slice frame of ``images`` (pixel
            ``(r, c)`` at ``x = (c - (W-1)/2) col_mm``, ``y = (r - (H-1)/2) row_mm``).
        active: ``[n]`` slices that take part (their poses move); the others, and slices with
            fewer than :data:`MIN_BRAIN_PIXELS` brain pixels, keep their poses and do not take part.
    """

    images: NDArray[np.float32]
    masks: NDArray[np.bool_]
    pixel_mm: tuple[float, float]
    slice_from_network: NDArray[np.float64]
    active: NDArray[np.bool_]


@dataclass
class Refinement:
    """What the image term did to a request's poses."""

    poses: list[NDArray[np.float64]]      # per stack [n, 4, 4], network frame -> atlas
    moved_mm: list[NDArray[np.float64]]   # per stack [n]: how far each slice moved (E.D.-like, mm)
    pairs: int                            # intersecting pairs used
    cost_before: float                    # the image term per weighted point, before / after
    cost_after: float
    mismatch: list[NDArray[np.float64]]   # per stack [n]: each slice's image term per weighted point, after (NaN: none)


def pair_points(atlas_from_slice_a: NDArray, atlas_from_slice_b: NDArray, pairs: NDArray,
                t_mm: NDArray) -> NDArray[np.float64]:
    """``[M, N, 3]`` atlas points along the intersection line of each pair's planes.

    The line's points sit at ``t_mm`` from the point of the line nearest the midpoint of the two
    slices' origins (so the samples move smoothly with the poses). ``pairs`` indexes the two
    arrays of ``atlas_from_slice`` poses."""
    a, b = atlas_from_slice_a[pairs[:, 0]], atlas_from_slice_b[pairs[:, 1]]
    na, nb = a[:, :3, 2], b[:, :3, 2]
    oa, ob = a[:, :3, 3], b[:, :3, 3]
    d = np.cross(na, nb)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    m = 0.5 * (oa + ob)
    lhs = np.stack([na, nb, d], axis=1)                                     # [M, 3, 3]
    rhs = np.stack([np.sum(na * oa, 1), np.sum(nb * ob, 1), np.sum(d * m, 1)], axis=1)
    p0 = np.linalg.solve(lhs, rhs[..., None])[..., 0]
    return p0[:, None, :] + t_mm[None, :, None] * d[:, None, :]


class _Stack:
    """A stack's smoothed, scaled images and masks, sampled at atlas points (bilinear)."""

    def __init__(self, s: StackImages, sigma_mm: float) -> None:
        brain = s.images[s.masks]
        scale = float(np.median(brain)) if brain.size else 1.0
        sig = (0.0, sigma_mm / s.pixel_mm[0], sigma_mm / s.pixel_mm[1])
        images = s.images.astype(np.float32) / max(scale, 1e-6)
        self.images = ndimage.gaussian_filter(images, sig)
        self.masks = ndimage.gaussian_filter(s.masks.astype(np.float32), (0.0, 1.0, 1.0))
        pad = ((0, 0), (1, 1), (1, 1))                                      # a zero border: bilinear fades to 0
        self.images_flat = np.pad(self.images, pad).ravel()
        self.masks_flat = np.pad(self.masks, pad).ravel()
        self.padded = (s.images.shape[1] + 2, s.images.shape[2] + 2)
        n, h, w = s.images.shape
        self.pixel_from_slice = np.array([[0.0, 1.0 / s.pixel_mm[0], 0.0, (h - 1) / 2.0],    # row
                                          [1.0 / s.pixel_mm[1], 0.0, 0.0, (w - 1) / 2.0]])  # column

    def line_pixels(self, slice_from_atlas: NDArray, line: NDArray) -> NDArray[np.float64]:
        """``[M, 2, 2]`` (row, column) of two atlas points ``line`` ``[M, 2, 3]`` in slices whose
        ``slice_from_atlas`` are ``[M, 4, 4]``."""
        pixel_from_atlas = np.einsum("ij,mjk->mik", self.pixel_from_slice, slice_from_atlas)   # [M, 2, 4]
        return np.einsum("mij,mej->mei", pixel_from_atlas[:, :, :3], line) + pixel_from_atlas[:, None, :, 3]

    def sample(self, which: NDArray, rc: NDArray, masks: bool = False) -> NDArray[np.float32]:
        """Values of slices ``which`` ``[P]`` at pixels ``rc`` ``[P, 2]`` (bilinear; 0 beyond the
        image, fading over its border pixel)."""
        flat, (h, w) = (self.masks_flat if masks else self.images_flat), self.padded
        r, c = rc[:, 0] + 1.0, rc[:, 1] + 1.0
        inside = (r >= 0) & (r < h - 1) & (c >= 0) & (c < w - 1)
        r, c = np.clip(r, 0, h - 1.001), np.clip(c, 0, w - 1.001)
        r0, c0 = r.astype(np.int64), c.astype(np.int64)
        fr, fc = (r - r0).astype(np.float32), (c - c0).astype(np.float32)
        i = which.astype(np.int64) * (h * w) + r0 * w + c0
        top = flat[i] + fc * (flat[i + 1] - flat[i])
        bottom = flat[i + w] + fc * (flat[i + w + 1] - flat[i + w])
        return np.where(inside, top + fr * (bottom - top), 0.0).astype(np.float32)


def _prior_sd(sd_mm: NDArray) -> NDArray[np.float64]:
    """``[K, 6]`` per-coordinate prior sd of a slice's twist (rotation rad, translation mm) from its
    expected E.D.: the squared error shared out evenly over six coordinates."""
    e = np.asarray(sd_mm, dtype=np.float64)[:, None] / np.sqrt(6.0)
    return np.concatenate([np.repeat(e / ANCHOR_RADIUS_MM, 3, axis=1), np.repeat(e, 3, axis=1)], axis=1)


def candidate_pairs(atlas_from_slice: NDArray, stack_of: NDArray, free: NDArray) -> NDArray[np.int64]:
    """``[M, 2]`` pairs of free slices of different stacks (first of the lower stack) whose planes
    cross at :data:`MIN_SINE` or more."""
    idx = np.flatnonzero(free)
    a, b = np.meshgrid(idx, idx, indexing="ij")
    a, b = a.ravel(), b.ravel()
    keep = stack_of[a] < stack_of[b]
    a, b = a[keep], b[keep]
    sine = np.linalg.norm(np.cross(atlas_from_slice[a, :3, 2], atlas_from_slice[b, :3, 2]), axis=1)
    keep = sine >= MIN_SINE
    return np.stack([a[keep], b[keep]], axis=1)


def refine(stacks: list[StackImages], poses: list[NDArray], sd_mm: list[NDArray], *,
           sigmas_mm: tuple[float, ...] = SIGMAS_MM, spacing_mm: float = 2.0, noise: float = 0.15,
           prior_weight: float = 1.0, iterations: int = 8) -> Refinement:
    """Refine every free slice's pose so that slices of different stacks agree where they cross.

    Args:
        stacks: each stack's images (:class:`StackImages`).
        poses: each stack's poses ``[n, 4, 4]`` (network frame -> atlas), the stage's output.
        sd_mm: each stack's expected E.D. per slice ``[n]`` (the prior's scale; non-finite: 10 mm).
        sigmas_mm: in-plane smoothing of each pass, coarse to fine.
        spacing_mm: spacing of the points along each intersection line.
        noise: the intensity difference (in units of a stack's median brain intensity) that counts
            as one standard deviation; the soft-L1 loss turns linear beyond it.
        prior_weight: multiplies the prior's residuals (1: the stage's expected errors as they are).
        iterations: Gauss-Newton iterations per pass.

    Returns:
        :class:`Refinement`; a request with fewer than two stacks, or no crossing pairs, comes back
        unchanged.
    """
    sizes = [len(p) for p in poses]
    bounds = np.cumsum([0, *sizes])
    unchanged = Refinement([p.copy() for p in poses], [np.zeros(n) for n in sizes], 0, np.nan, np.nan,
                           [np.full(n, np.nan) for n in sizes])
    if len(stacks) < 2:
        return unchanged
    stack_of = np.repeat(np.arange(len(stacks)), sizes)
    local = np.concatenate([np.arange(n) for n in sizes])
    p0 = np.concatenate(poses)
    network_from_slice = se3.inverse(np.concatenate([s.slice_from_network for s in stacks]))
    pixels = np.concatenate([s.masks.reshape(len(s.masks), -1).sum(axis=1) for s in stacks])
    free = (pixels >= MIN_BRAIN_PIXELS) & np.concatenate([s.active for s in stacks])
    if not free.any():
        return unchanged
    col = -np.ones(len(p0), int)
    col[free] = np.arange(free.sum())
    sd = np.concatenate([np.where(np.isfinite(e), e, 10.0) for e in sd_mm])
    prior = _prior_sd(np.maximum(sd[free], 0.5)) / prior_weight            # [F, 6]
    radius = max(_brain_radius(s) for s in stacks)
    x = np.zeros((int(free.sum()), 6))

    def atlas_from_slice(params: NDArray) -> NDArray:
        twist = np.zeros((len(p0), 6))
        twist[free] = params
        return p0 @ se3.exp(twist) @ network_from_slice

    pairs = candidate_pairs(atlas_from_slice(x), stack_of, free)
    if not len(pairs):
        return unchanged
    costs: list[float] = []
    used = 0
    mismatch = np.full(len(p0), np.nan)
    for sigma in sigmas_mm:
        step = max(spacing_mm, sigma)                                   # a smoother pass needs fewer points
        t = np.arange(-radius, radius + 1e-9, step)
        term = _ImageTerm([_Stack(s, sigma) for s in stacks], stack_of, local, pairs, t)
        w = np.clip(np.prod(term.values(atlas_from_slice(x), masks=True), axis=0), 0.0, 1.0).astype(np.float64)
        term.select(w, min_weight=MIN_LINE_WEIGHT)
        if not len(term.pair_of):
            break
        used = len(term.pairs)
        def residual(params: NDArray, stack: int | None = None, term: _ImageTerm = term) -> NDArray:
            part = term if stack is None else term.restricted(stack)[0]
            return part.residuals(atlas_from_slice(params)) / noise

        costs.append(_mean_square(residual(x), term.sw))
        x = _gauss_newton(residual, lambda k, term=term: term.restricted(k)[1], x, prior, col, stack_of,
                          term.pairs[term.pair_of], iterations)
        r = residual(x)
        costs.append(_mean_square(r, term.sw))
        mismatch = _per_slice(r, term.sw, term.pairs[term.pair_of], len(p0))
    final = atlas_from_slice(x) @ se3.inverse(network_from_slice)
    checked = np.isfinite(mismatch)
    if not checked.any():
        return unchanged
    final = follow_neighbours(final, p0, checked, stack_of, local)
    # The images do not see the request's frame; it goes back where the stage's poses put it.
    frame = se3.frechet_mean(p0[checked] @ se3.inverse(final[checked]), 1.0 / np.maximum(sd[checked], 0.5) ** 2)
    final = frame @ final
    moved = ed(final, p0)
    cut = lambda a: [a[i:j] for i, j in zip(bounds[:-1], bounds[1:])]  # noqa: E731
    return Refinement(cut(final), cut(moved), used, costs[0] if costs else np.nan, costs[-1] if costs else np.nan,
                      cut(mismatch))


def _per_slice(r: NDArray, sw: NDArray, point_pairs: NDArray, n: int) -> NDArray[np.float64]:
    """``[n]`` each slice's weighted mean squared image residual over the points of its lines
    (NaN for a slice on no line)."""
    num = np.bincount(point_pairs[:, 0], r ** 2, n) + np.bincount(point_pairs[:, 1], r ** 2, n)
    den = np.bincount(point_pairs[:, 0], sw ** 2, n) + np.bincount(point_pairs[:, 1], sw ** 2, n)
    return np.where(den > 0, num / np.maximum(den, 1e-12), np.nan)


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
    for g in np.flatnonzero(~checked):
        mine = np.flatnonzero(checked & (stack_of == stack_of[g]))
        if not len(mine):
            continue
        below, above = mine[index[mine] < index[g]], mine[index[mine] > index[g]]
        near = [side[np.argmin(np.abs(index[side] - index[g]))] for side in (below, above) if len(side)]
        out[g] = se3.frechet_mean(correction[near], np.ones(len(near))) @ start[g]
    return out


def _mean_square(r: NDArray, sw: NDArray) -> float:
    return float(np.sum(r ** 2) / max(float(np.sum(sw ** 2)), 1e-12))


class _ImageTerm:
    """The image residuals of one pass: both slices' values at the chosen points of each pair's line."""

    def __init__(self, sampled: list[_Stack], stack_of: NDArray, local: NDArray, pairs: NDArray, t: NDArray) -> None:
        self.sampled, self.stack_of, self.local, self.pairs, self.t = sampled, stack_of, local, pairs, t
        self.pair_of = np.repeat(np.arange(len(pairs)), len(t))
        self.t_of = np.tile(np.arange(len(t)), len(pairs))
        self.sw = np.ones(len(self.pair_of))
        self._index()

    def select(self, w: NDArray, min_weight: float) -> None:
        """Keep the points of pairs whose lines cross both brains over ``min_weight`` points' worth,
        where both masks are (nearly) nonzero; weights fixed from here on."""
        total = np.bincount(self.pair_of, weights=w, minlength=len(self.pairs))
        keep = (w > 1e-3) & (total[self.pair_of] >= min_weight)
        count = np.bincount(self.pair_of[keep], minlength=len(self.pairs))
        if count.sum() > MAX_POINTS:               # many stacks: a fixed random share of the pairs, whole lines
            order = np.random.default_rng(0).permutation(len(self.pairs))
            chosen = np.zeros(len(self.pairs), bool)
            chosen[order[np.cumsum(count[order]) <= MAX_POINTS]] = True
            keep &= chosen[self.pair_of]
        used, pair_of = np.unique(self.pair_of[keep], return_inverse=True)
        self.pairs, self.pair_of, self.t_of, self.sw = self.pairs[used], pair_of, self.t_of[keep], np.sqrt(w[keep])
        self._index()

    def _index(self) -> None:
        """Per (role, stack): the pairs whose slice in that role is of that stack, and their points
        (what :meth:`values` gathers, worked out once per point set)."""
        self.groups, self._subs = [], {}
        for role in (0, 1):
            g = self.pairs[:, role]
            for s in range(len(self.sampled)):
                mine = np.flatnonzero(self.stack_of[g] == s)
                if not len(mine):
                    continue
                where = np.zeros(len(self.pairs), int)
                where[mine] = np.arange(len(mine))
                rows = np.flatnonzero(self.stack_of[g[self.pair_of]] == s)
                self.groups.append((role, s, mine, g[mine], rows, where[self.pair_of[rows]],
                                    self.local[g[self.pair_of[rows]]], self.t[self.t_of[rows]][:, None]))

    def values(self, atlas_from_slice: NDArray, masks: bool = False) -> NDArray[np.float32]:
        """``[2, P]`` both slices' values at each point (images, or masks)."""
        line = pair_points(atlas_from_slice, atlas_from_slice, self.pairs, np.array([0.0, 1.0]))   # base, base + d
        inv = se3.inverse(atlas_from_slice)
        out = np.zeros((2, len(self.pair_of)), np.float32)
        for role, s, mine, g, rows, pos, k, t in self.groups:
            ends = self.sampled[s].line_pixels(inv[g], line[mine])[pos]            # [P_s, 2, 2]
            out[role, rows] = self.sampled[s].sample(k, ends[:, 0] + t * (ends[:, 1] - ends[:, 0]), masks)
        return out

    def restricted(self, stack: int) -> tuple[_ImageTerm, NDArray[np.int64]]:
        """The term of the points whose pair has a slice in ``stack``, and their rows here: all
        that moving that stack's slices changes (cached)."""
        if stack not in self._subs:
            involved = (self.stack_of[self.pairs] == stack).any(axis=1)
            rows = np.flatnonzero(involved[self.pair_of])
            sub = copy.copy(self)
            used, sub.pair_of = np.unique(self.pair_of[rows], return_inverse=True)
            sub.pairs, sub.t_of, sub.sw, sub._subs = self.pairs[used], self.t_of[rows], self.sw[rows], {}
            sub._index()
            self._subs[stack] = (sub, rows)
        return self._subs[stack]

    def residuals(self, atlas_from_slice: NDArray) -> NDArray[np.float64]:
        va, vb = self.values(atlas_from_slice)
        return self.sw * (va.astype(np.float64) - vb)


def _gauss_newton(residual, rows_of, x: NDArray, prior: NDArray, col: NDArray, stack_of: NDArray,  # noqa: ANN001
                  point_pairs: NDArray, iterations: int) -> NDArray[np.float64]:
    """Levenberg-Marquardt on the soft-L1 image residuals plus the Gaussian prior ``x / prior``,
    with a forward-difference Jacobian in groups: one coordinate of every free slice of one stack
    at a time (no image residual involves two slices of one stack), each evaluated on the residuals
    that stack takes part in (``residual(params, stack)``, rows ``rows_of(stack)``)."""
    steps = np.array([5e-3, 5e-3, 5e-3, 0.2, 0.2, 0.2])
    cols = col[point_pairs]                                                # [P, 2] parameter row of each slice
    stack_free = stack_of[col >= 0][np.argsort(col[col >= 0])]              # the stack of each parameter row
    stacks_pp = stack_of[point_pairs]
    n = x.size

    def cost(r: NDArray, params: NDArray) -> float:
        return float(np.sum(2.0 * (np.sqrt(1.0 + r ** 2) - 1.0)) + np.sum((params / prior) ** 2))

    r = residual(x)
    c = cost(r, x)
    mu = 1e-3
    for _ in range(iterations):
        rows, cidx, vals = [], [], []
        for s in np.unique(stack_free):
            part = rows_of(s)
            for j in range(6):
                dx = np.zeros_like(x)
                dx[:, j] = steps[j]
                dr = np.zeros(len(r))
                dr[part] = (residual(x + dx * (stack_free == s)[:, None], s) - r[part]) / steps[j]
                for role in (0, 1):
                    hit = np.flatnonzero((stacks_pp[:, role] == s) & (cols[:, role] >= 0))
                    rows.append(hit)
                    cidx.append(6 * cols[hit, role] + j)
                    vals.append(dr[hit])
        jac = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cidx))),
                                shape=(len(r), n))
        omega = 1.0 / np.sqrt(1.0 + r ** 2)                                 # IRLS weights of the soft-L1 loss
        jw = jac.multiply(omega[:, None]).tocsr()
        hess = (jac.T @ jw).toarray() + np.diag(1.0 / prior.ravel() ** 2)
        grad = jw.T @ r + (x / prior ** 2).ravel()
        while True:
            step = np.linalg.solve(hess + mu * np.diag(np.diag(hess)), -grad)
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
                return x
        if done:
            break
    return x


def _brain_radius(s: StackImages) -> float:
    """The largest distance (mm) of a brain pixel from its slice's network origin, over the stack."""
    k, r, c = np.nonzero(s.masks)
    if not len(k):
        return 0.0
    h, w = s.masks.shape[1:]
    x = (c - (w - 1) / 2.0) * s.pixel_mm[1] - s.slice_from_network[k, 0, 3]
    y = (r - (h - 1) / 2.0) * s.pixel_mm[0] - s.slice_from_network[k, 1, 3]
    return float(np.sqrt(x ** 2 + y ** 2).max())


def expected_after(expected_mm: list[NDArray], mismatch: list[NDArray]) -> list[NDArray[np.float64]]:
    """Each slice's expected E.D. after :func:`refine`, from the stage's (``expected_mm``) and the
    slice's remaining image mismatch relative to the request's median (:data:`REFINED_GAIN`,
    :data:`UNCHECKED_GAIN`).

    Example:
        >>> [e.round(2).tolist() for e in expected_after([np.array([4.0, 4.0, 4.0])], [np.array([1.0, 4.0, np.nan])])]
        [[1.64, 3.29, 7.6]]
    """
    every = np.concatenate([m for m in mismatch]) if mismatch else np.zeros(0)
    ref = float(np.nanmedian(every)) if np.isfinite(every).any() else np.nan
    out = []
    for e, m in zip(expected_mm, mismatch):
        ratio = np.sqrt(np.maximum(m, 0.0) / max(ref, 1e-12)) if np.isfinite(ref) else np.full(len(m), np.nan)
        out.append(np.where(np.isfinite(ratio), REFINED_GAIN * e * ratio, UNCHECKED_GAIN * np.asarray(e, np.float64)))
    return out
