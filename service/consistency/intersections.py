"""Where slices of different stacks cross, and what their images show there.

Two slices of differently oriented stacks cut the brain along a common line. At their true poses
both images show the same tissue there; at wrong poses they show different tissue (Kim et al.,
IEEE TMI 2010, "Intersection based motion correction of multislice MRI"). This module holds the
geometry of those lines and the image term of :mod:`service.consistency.image_refinement`:

::

    sum over pairs (a, b) of slices of different stacks, points x_i on their intersection line:
        w_i (I_a(x_i) - I_b(x_i))^2 / sigma^2

``I_a`` is slice ``a``'s image (bias-corrected, scaled by its stack's median brain intensity,
smoothed in-plane: :mod:`service.consistency.slice_images`; divided by its stack's fitted intensity
field from the refinement's second pass on: :mod:`service.consistency.intensity_match`), sampled
bilinearly; ``w_i`` the product of both slices' brain masks at ``x_i``, fixed once chosen (a weight
that followed the poses would reward moving the lines out of the brain).

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

from service.consistency.slice_images import Cells, SampledStack, SampledStacks
from service.geometry import se3

MIN_SINE = np.sin(np.radians(30.0))
"""Pairs whose planes meet at less than this angle are left out (their line is ill-placed)."""
MAX_POINTS = 25_000
"""Points per pass at most: a fixed random share of the crossing pairs (their lines whole) bounds
the time, whatever the stacks: three stacks of a fetal brain may cross at fewer or at several
times as many points. The poses improve a little with more, at a cost in time, and lose more with fewer (the runs:
docs/reports/benchmark-history.md)."""


@dataclass
class Lines:
    """The intersection line of each pair's planes (``[M, ...]``): the planes' normals ``na``, ``nb``
    and origins ``oa``, ``ob``, the line's direction ``d = cross / size`` (``cross = na x nb``), the
    midpoint ``m`` of the origins, and the line's point ``p`` nearest it: ``L p = rhs`` for ``L`` the
    rows ``na, nb, d`` and ``rhs = (na . oa, nb . ob, d . m)``. ``inv`` is ``L``'s inverse, in closed
    form: its columns are ``nb x d`` and ``d x na`` over ``size``, and ``d``, since ``d`` is a unit
    vector normal to both normals and ``L``'s determinant is ``d . (na x nb) = size``."""

    na: NDArray[np.float64]
    nb: NDArray[np.float64]
    oa: NDArray[np.float64]
    ob: NDArray[np.float64]
    d: NDArray[np.float64]
    size: NDArray[np.float64]
    m: NDArray[np.float64]
    inv: NDArray[np.float64]
    p: NDArray[np.float64]


def lines(atlas_from_slice_a: NDArray, atlas_from_slice_b: NDArray, pairs: NDArray) -> Lines:
    """The intersection line of each pair's planes; ``pairs`` indexes the two arrays of
    ``atlas_from_slice`` poses."""
    a, b = atlas_from_slice_a[pairs[:, 0]], atlas_from_slice_b[pairs[:, 1]]
    na, nb = a[:, :3, 2], b[:, :3, 2]
    oa, ob = a[:, :3, 3], b[:, :3, 3]
    cross = np.cross(na, nb)
    size = np.maximum(np.linalg.norm(cross, axis=1), 1e-12)
    d = cross / size[:, None]
    m = 0.5 * (oa + ob)
    rhs = np.stack([np.sum(na * oa, 1), np.sum(nb * ob, 1), np.sum(d * m, 1)], axis=1)
    inv = np.stack([np.cross(nb, d) / size[:, None], np.cross(d, na) / size[:, None], d], axis=2)    # [M, 3, 3]
    return Lines(na, nb, oa, ob, d, size, m, inv, (inv @ rhs[..., None])[..., 0])


def pair_points(atlas_from_slice_a: NDArray, atlas_from_slice_b: NDArray, pairs: NDArray,
                t_mm: NDArray) -> NDArray[np.float64]:
    """``[M, N, 3]`` atlas points along the intersection line of each pair's planes.

    The line's points sit at ``t_mm`` from the point of the line nearest the midpoint of the two
    slices' origins (so the samples move smoothly with the poses). ``pairs`` indexes the two
    arrays of ``atlas_from_slice`` poses."""
    ln = lines(atlas_from_slice_a, atlas_from_slice_b, pairs)
    return ln.p[:, None, :] + t_mm[None, :, None] * ln.d[:, None, :]


def candidate_pairs(atlas_from_slice: NDArray, stack_of: NDArray, free: NDArray) -> NDArray[np.int64]:
    """``[M, 2]`` pairs of slices of different stacks that take part (``free``; first of the lower
    stack) whose planes cross at :data:`MIN_SINE` or more."""
    idx = np.flatnonzero(free)
    a, b = np.meshgrid(idx, idx, indexing="ij")
    a, b = a.ravel(), b.ravel()
    keep = stack_of[a] < stack_of[b]
    a, b = a[keep], b[keep]
    sine = np.linalg.norm(np.cross(atlas_from_slice[a, :3, 2], atlas_from_slice[b, :3, 2]), axis=1)
    keep = sine >= MIN_SINE
    return np.stack([a[keep], b[keep]], axis=1)


def slice_keys(stack_of: NDArray, local: NDArray, fingerprints: list[NDArray]) -> NDArray[np.uint64]:
    """``[n]`` a 64-bit hash naming each slice by its own fingerprint (per stack, ``[n_s]`` checksums
    of its slices' masks): the same whatever the stack's place in the request, and wherever the file
    stores the slice within its stack (slices last to first). Slices of identical masks (one box
    uploaded for every slice) share a key, and their pairs keep the order they are listed in."""
    flat = np.concatenate([np.asarray(f, np.uint64) for f in fingerprints])
    start = np.cumsum([0] + [len(f) for f in fingerprints])[:-1]
    return _mix(flat[start[np.asarray(stack_of)] + np.asarray(local)])


def canonical_pairs(pairs: NDArray, keys: NDArray) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The ``pairs`` each with its slice of the smaller key (:func:`slice_keys`) first, and each
    pair's place in the point budget's fixed random order (the order of a hash of its two keys).
    A pair's line, its points and the budget's choice of pairs then depend on its two slices alone,
    not on the order of the request's stacks: the same stacks sent in another order get the same poses.

    Example (two stacks of three slices, then the same stacks the other way round):
        >>> pairs = np.array([[0, 3], [0, 4], [1, 5], [2, 3]])
        >>> keys = slice_keys(np.repeat([0, 1], 3), np.tile(np.arange(3), 2), [[11, 12, 13], [21, 22, 23]])
        >>> swapped = np.concatenate([keys[3:], keys[:3]])          # stack 1 first
        >>> a, rank_a = canonical_pairs(pairs, keys)
        >>> b, rank_b = canonical_pairs((pairs + 3) % 6, swapped)
        >>> bool((keys[a] == swapped[b]).all() and (rank_a == rank_b).all()), sorted(rank_a.tolist())
        (True, [0, 1, 2, 3])
    """
    pairs = np.asarray(pairs, np.int64)
    a, b = keys[pairs[:, 0]], keys[pairs[:, 1]]
    pairs = np.where((a <= b)[:, None], pairs, pairs[:, ::-1])
    rank = np.empty(len(pairs), np.int64)
    rank[np.argsort(_mix(np.minimum(a, b) ^ _mix(np.maximum(a, b))), kind="stable")] = np.arange(len(pairs))
    return pairs, rank


def _mix(z: NDArray) -> NDArray[np.uint64]:
    """SplitMix64's finaliser on ``uint64`` arrays (wrapping): well-spread 64-bit hashes of integers."""
    z = np.asarray(z, np.uint64)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


BOX_MARGIN_PX = 1.5
"""A slice's mask box is widened by this many pixels before a line's points are tested against it:
a bilinear sample reads the pixels up to one away, and the margin's rest covers rounding."""


class ImageTerm:
    """The image residuals of one pass: both slices' values at the chosen points of each pair's line.

    Every point of every pair is found and sampled in one set of array operations per role (the
    pair's first or second slice), whatever stack its slice is of
    (:class:`~service.consistency.slice_images.SampledStacks`), in one thread: a pass's tens of
    thousands of points take a few milliseconds, less than handing half of them to another thread
    gains. The points' slices are kept until the points change, and their places among the pixels
    at the last poses asked for: the Jacobian at a set of poses follows the residuals at the same
    poses."""

    def __init__(self, sampled: list[SampledStack], stack_of: NDArray, local: NDArray, pairs: NDArray, t: NDArray,
                 atlas_from_slice: NDArray | None = None) -> None:
        """The points at ``t`` (mm, ascending) along each pair's line; with ``atlas_from_slice``, only
        those within both slices' mask boxes at those poses (:meth:`_within_boxes`): elsewhere a
        point's weight is 0, and :meth:`select` would drop it."""
        self.stacks = SampledStacks(sampled)
        pairs, self._rank = canonical_pairs(pairs, slice_keys(stack_of, local, [s.fingerprints for s in sampled]))
        self.stack_of, self.local, self.pairs, self.t = stack_of, local, pairs, t
        first, count = np.zeros(len(pairs), np.int64), np.full(len(pairs), len(t))
        if atlas_from_slice is not None:
            lo, hi = self._within_boxes(atlas_from_slice)
            first = np.searchsorted(t, lo, side="left")
            count = np.maximum(np.searchsorted(t, hi, side="right") - first, 0)
        self.pair_of = np.repeat(np.arange(len(pairs)), count)
        self.t_of = first[self.pair_of] + np.arange(len(self.pair_of)) - np.repeat(np.cumsum(count) - count, count)
        self.sw = np.ones(len(self.pair_of))
        self._last: tuple | None = None
        self._slices: list[tuple | None] = [None, None]

    def select_in_masks(self, atlas_from_slice: NDArray, min_weight: float, max_points: int | None = None) -> None:
        """:meth:`select` with the weights of the slices' masks at the poses ``atlas_from_slice``
        (the product of both masks at each point, clipped to 0..1).

        Where the point budget binds, the pairs are sampled in the budget's order until it is
        spent (a request of six stacks crosses at ten times the budget's points): the choice is
        :meth:`select`'s on every point's weight."""
        max_points = MAX_POINTS if max_points is None else max_points
        order = np.argsort(self._rank)
        bound = np.bincount(self.pair_of, minlength=len(self.pairs))[order]     # each pair's points at most
        w = np.full(len(self.pair_of), np.nan)
        done, kept = 0, 0
        while done < len(order) and kept <= max_points:
            stop = done + 1 + int(np.searchsorted(np.cumsum(bound[done:]), 1.5 * (max_points + 1 - kept)))
            batch = np.zeros(len(self.pairs), bool)
            batch[order[done:stop]] = True
            points = batch[self.pair_of]
            part = copy.copy(self)
            part._keep(points)
            w[points] = np.clip(np.prod(part.values(atlas_from_slice, masks=True), axis=0), 0.0, 1.0)
            kept += int(part._kept(w[points], min_weight).sum())
            done = stop
        self.select(w, min_weight, max_points)

    def _within_boxes(self, atlas_from_slice: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``[M]`` twice: the interval of ``t`` (mm) where each pair's line lies within both its
        slices' mask boxes (widened by :data:`BOX_MARGIN_PX`; empty: lo > hi). A line's pixel in a
        slice is linear in ``t``: it stays inside the box between where it enters and leaves it."""
        lo, hi = np.full(len(self.pairs), -np.inf), np.full(len(self.pairs), np.inf)
        for role, ends in enumerate(self._line_ends(atlas_from_slice)):
            g = self.pairs[:, role]
            box = self.stacks.support[self.stacks.first_slice[self.stack_of[g]] + self.local[g]]   # [M, 2, 2]
            start, slope = ends[:, 0], ends[:, 1] - ends[:, 0]
            low, high = box[:, :, 0] - BOX_MARGIN_PX, box[:, :, 1] + BOX_MARGIN_PX
            on = (start >= low) & (start <= high)
            flat = np.abs(slope) < 1e-12
            with np.errstate(divide="ignore", invalid="ignore"):
                a, b = (low - start) / slope, (high - start) / slope
            enter = np.where(flat, np.where(on, -np.inf, np.inf), np.minimum(a, b))
            leave = np.where(flat, np.where(on, np.inf, -np.inf), np.maximum(a, b))
            lo, hi = np.maximum(lo, enter.max(axis=1)), np.minimum(hi, leave.min(axis=1))
        return lo, hi

    def _line_ends(self, atlas_from_slice: NDArray) -> list[NDArray[np.float64]]:
        """Per role, where each pair's line's base point and the point 1 mm along it fall in that
        slice's pixels (``[M, 2, 2]``: row, column): a line's pixel in a slice is linear in ``t``
        between them."""
        line = pair_points(atlas_from_slice, atlas_from_slice, self.pairs, np.array([0.0, 1.0]))
        slice_from_atlas = se3.inverse(atlas_from_slice)
        ends = []
        for role in (0, 1):
            g = self.pairs[:, role]
            pixel_from_atlas = self.stacks.pixel_from_slice[self.stack_of[g]] @ slice_from_atlas[g]   # [M, 2, 4]
            ends.append(line @ np.swapaxes(pixel_from_atlas[:, :, :3], 1, 2) + pixel_from_atlas[:, None, :, 3])
        return ends

    def _keep(self, keep: NDArray, sw: NDArray | None = None) -> None:
        """Keep the points ``keep`` (and the pairs that still have one); ``sw``: their weights' square roots."""
        pair_of = self.pair_of[keep]
        used = np.bincount(pair_of, minlength=len(self.pairs)) > 0
        self.pairs, self.pair_of, self.t_of = self.pairs[used], (np.cumsum(used) - 1)[pair_of], self.t_of[keep]
        self._rank = self._rank[used]
        self.sw = self.sw[keep] if sw is None else sw
        self._last = None
        self._slices = [None, None]

    def select(self, w: NDArray, min_weight: float, max_points: int | None = None) -> None:
        """Keep the points of pairs whose lines cross both brains over ``min_weight`` points' worth,
        where both masks are (nearly) nonzero, at most ``max_points`` (default :data:`MAX_POINTS`;
        whole lines, the pairs in a fixed random order); weights fixed from here on. A pair whose
        weights are NaN (not sampled) is left out."""
        max_points = MAX_POINTS if max_points is None else max_points
        w = np.where(np.isfinite(w), w, 0.0)
        keep = self._kept(w, min_weight)
        count = np.bincount(self.pair_of[keep], minlength=len(self.pairs))
        if count.sum() > max_points:               # many stacks: a fixed random share of the pairs, whole lines
            order = np.argsort(self._rank)
            chosen = np.zeros(len(self.pairs), bool)
            chosen[order[np.cumsum(count[order]) <= max_points]] = True
            keep &= chosen[self.pair_of]
        self._keep(keep, np.sqrt(w[keep]))

    def _kept(self, w: NDArray, min_weight: float) -> NDArray[np.bool_]:
        """``[P]`` the points of weight over 1e-3 on lines of ``min_weight`` points' worth or more."""
        total = np.bincount(self.pair_of, weights=w, minlength=len(self.pairs))
        return (w > 1e-3) & (total[self.pair_of] >= min_weight)

    def _where(self, atlas_from_slice: NDArray) -> list[tuple[NDArray, Cells]]:
        """Per role, each point's slice and where it falls among that slice's pixels (:class:`Cells`)."""
        if self._last is not None and np.array_equal(self._last[0], atlas_from_slice):
            return self._last[1]
        at = self.pixels(atlas_from_slice)

        def site(role: int) -> tuple[NDArray, Cells]:
            slices, start, h, w = self._slices_of_points(role)
            return slices, self.stacks.cells_from(start, h, w, at[role, :, 0], at[role, :, 1])

        sites = [site(0), site(1)]
        self._last = (np.array(atlas_from_slice, copy=True), sites)
        return sites

    def pixels(self, atlas_from_slice: NDArray) -> NDArray[np.float64]:
        """``[2, P, 2]`` where each point falls in each role's slice: (row, column) of its stack's
        images (:class:`~service.consistency.slice_images.SampledStack`'s grid)."""
        ends = self._line_ends(atlas_from_slice)
        t = self.t[self.t_of]
        out = np.empty((2, len(t), 2))
        for role in (0, 1):
            base, slope = ends[role][:, 0].T, (ends[role][:, 1] - ends[role][:, 0]).T      # [2, M]: rows, columns
            for k in (0, 1):
                out[role, :, k] = base[k][self.pair_of] + t * slope[k][self.pair_of]
        return out

    def use_images(self, sampled: list[SampledStack]) -> None:
        """Sample ``sampled`` (the same stacks on the same grids, other values) from here on; the
        points and their weights stay."""
        self.stacks = SampledStacks(sampled)
        self._last = None
        self._slices = [None, None]

    def _slices_of_points(self, role: int) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Each point's slice in ``role``, where that slice starts in the flat arrays and its padded
        size (:meth:`~service.consistency.slice_images.SampledStacks.layout`): the same at every
        pose, so kept until the points change."""
        if self._slices[role] is None:
            slices = self.pairs[:, role][self.pair_of]
            self._slices[role] = (slices, *self.stacks.layout(self.stack_of[slices], self.local[slices]))
        return self._slices[role]

    def values(self, atlas_from_slice: NDArray, masks: bool = False) -> NDArray[np.float32]:
        """``[2, P]`` both slices' values at each point (images, or masks)."""
        sites = self._where(atlas_from_slice)
        flat = self.stacks.masks if masks else self.stacks.images
        return np.stack([self.stacks.sample(flat, sites[role][1]) for role in (0, 1)])

    def gradients(self, atlas_from_slice: NDArray) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
        """Both slices' image gradients at each point, in two factors: ``[2, P, 2]`` each point's
        derivatives along its slice's pixel rows and columns, and ``[2, M, 3, 2]`` the atlas gradient
        of the row and column coordinate of each pair's slice (pixels per mm). A point's image
        gradient (per atlas mm, in its slice's plane) is ``along[role, pair] @ pixel[role, point]``:
        what the residuals' derivatives need besides the geometry."""
        sites = self._where(atlas_from_slice)
        along = atlas_from_slice[:, :3, :3] @ np.swapaxes(self.stacks.pixel_from_slice[self.stack_of][:, :, :3], 1, 2)
        pixel = np.stack([np.stack([self.stacks.sample(flat, sites[role][1])
                                    for flat in (self.stacks.gradient_rows, self.stacks.gradient_cols)], axis=1)
                          for role in (0, 1)])
        return pixel, np.stack([along[self.pairs[:, 0]], along[self.pairs[:, 1]]])

    def residuals(self, atlas_from_slice: NDArray) -> NDArray[np.float64]:
        va, vb = self.values(atlas_from_slice)
        return self.sw * (va.astype(np.float64) - vb)
