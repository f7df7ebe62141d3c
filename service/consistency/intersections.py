"""Where slices of different stacks cross, and what their images show there.

Two slices of differently oriented stacks cut the brain along a common line. At their true poses
both images show the same tissue there; at wrong poses they show different tissue (Kim et al.,
IEEE TMI 2010, "Intersection based motion correction of multislice MRI"). This module holds the
geometry of those lines and the image term of :mod:`service.consistency.image_refinement`:

::

    sum over pairs (a, b) of slices of different stacks, points x_i on their intersection line:
        w_i (I_a(x_i) - I_b(x_i))^2 / sigma^2

``I_a`` is slice ``a``'s image (bias-corrected, scaled by its stack's median brain intensity,
smoothed in-plane), sampled bilinearly; ``w_i`` the product of both slices' brain masks at ``x_i``,
fixed once chosen (a weight that followed the poses would reward moving the lines out of the brain).

Example:
    >>> import numpy as np
    >>> from service.geometry.pose import make_pose
    >>> axial = make_pose(np.eye(3), [0.0, 0.0, 5.0])                  # the plane z = 5
    >>> coronal = make_pose(se3.so3_exp([np.pi / 2, 0.0, 0.0]), [0.0, 2.0, 0.0])   # the plane y = 2
    >>> pair_points(axial[None], coronal[None], np.array([[0, 0]]), np.array([-10.0, 0.0, 10.0])).round(6).tolist()
    [[[-10.0, 2.0, 5.0], [0.0, 2.0, 5.0], [10.0, 2.0, 5.0]]]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from service.geometry import se3

MIN_SINE = np.sin(np.radians(30.0))
"""Pairs whose planes meet at less than this angle are left out (their line is ill-placed)."""
MAX_POINTS = 25_000
"""Points per pass at most: a fixed random share of the crossing pairs (their lines whole) bounds
the time. Three stacks of a fetal brain cross at about 7,000-60,000 points; the poses improve a
little with more (docs/benchmarks.md: 15,000 cost 0.2 mm at moderate motion, 35,000 gain 0.05 mm
for 15 % more time)."""


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
            fewer than :data:`~service.consistency.image_refinement.MIN_BRAIN_PIXELS` brain
            pixels, keep their poses and do not take part.
        fixed: the stack's active slices take part as fixed partners: the other stacks' slices
            are refined against them, they keep their poses.
    """

    images: NDArray[np.float32]
    masks: NDArray[np.bool_]
    pixel_mm: tuple[float, float]
    slice_from_network: NDArray[np.float64]
    active: NDArray[np.bool_]
    fixed: bool = False


@dataclass
class Lines:
    """The intersection line of each pair's planes (``[M, ...]``): the planes' normals ``na``, ``nb``
    and origins ``oa``, ``ob``, the line's direction ``d = cross / size`` (``cross = na x nb``), the
    midpoint ``m`` of the origins, and the line's point ``p`` nearest it (``lhs @ p = rhs``, ``lhs``
    the rows ``na, nb, d``)."""

    na: NDArray[np.float64]
    nb: NDArray[np.float64]
    oa: NDArray[np.float64]
    ob: NDArray[np.float64]
    d: NDArray[np.float64]
    size: NDArray[np.float64]
    m: NDArray[np.float64]
    lhs: NDArray[np.float64]
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
    lhs = np.stack([na, nb, d], axis=1)                                     # [M, 3, 3]
    rhs = np.stack([np.sum(na * oa, 1), np.sum(nb * ob, 1), np.sum(d * m, 1)], axis=1)
    return Lines(na, nb, oa, ob, d, size, m, lhs, np.linalg.solve(lhs, rhs[..., None])[..., 0])


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


SHADING_SCALE_MM = 6.0
"""The in-plane reach (Gaussian sigma, mm) of a slice's local brain mean (:func:`shading`); None: no
shading correction."""
SHADING_RANGE = (0.8, 1.25)
"""The local brain mean, over the stack's median, that counts as anatomy (:func:`shading`): on
noise-free atlas brains at their true poses the refinement then moves the slices no further than
without the correction (docs/consistency.md)."""
CROP_MARGIN_MM = 15.0
"""The images are kept this far beyond the union of a stack's brain masks (in-plane): the points'
moves and three sigmas of the widest smoothing (4.5 mm) stay inside it, so the crop changes the
finer passes' values not at all and the coarsest pass's through the Gaussian's tails beyond three
sigmas only (0.3 % of its weight)."""


@dataclass
class BlockedStack:
    """A stack's images scaled by its median brain intensity, and its masks, averaged over blocks of
    ``factors`` pixels (pixels finer than ~1 mm: the finest pass smooths at 0.9 mm anyway) and cut
    to its brain's in-plane box plus :data:`CROP_MARGIN_MM` (a whole-uterus slice of 320 x 320
    pixels holds the brain in a tenth of them); worked out once per request and shared by the passes.

    ``origin`` is the first original pixel ``(row, column)`` the blocks start at (a multiple of
    ``factors``).

    Example (a 64 x 64 slice whose brain is a 4 x 4 square, 1 mm pixels: 15 mm around it kept):
        >>> import numpy as np
        >>> m = np.zeros((1, 64, 64), bool); m[0, 30:34, 30:34] = True
        >>> b = BlockedStack.of(StackImages(np.ones((1, 64, 64), np.float32), m, (1.0, 1.0), np.eye(4)[None], np.ones(1, bool)))
        >>> b.images.shape, b.origin
        ((1, 34, 34), (15, 15))
    """

    images: NDArray[np.float32]
    masks: NDArray[np.float32]
    """The masks averaged over blocks, then smoothed by one block: the points' weights in every pass."""
    factors: tuple[int, int]
    origin: tuple[int, int]

    @classmethod
    def of(cls, s: StackImages) -> "BlockedStack":
        brain = s.images[s.masks]
        scale = float(np.median(brain)) if brain.size else 1.0
        f = (max(1, round(1.0 / s.pixel_mm[0])), max(1, round(1.0 / s.pixel_mm[1])))
        h, w = s.images.shape[1:]
        box = [slice(0, h), slice(0, w)]
        found = s.masks.any(axis=0)
        if found.any():
            for axis in (0, 1):
                hit = np.flatnonzero(found.any(axis=1 - axis))
                margin = int(np.ceil(CROP_MARGIN_MM / s.pixel_mm[axis]))
                lo = int(max(hit[0] - margin, 0) // f[axis] * f[axis])
                box[axis] = slice(lo, int(min(hit[-1] + margin + 1, (h, w)[axis])))
        images, masks = s.images[:, box[0], box[1]], s.masks[:, box[0], box[1]]
        images = _blocks(images.astype(np.float32) / max(scale, 1e-6), f)
        masks = _blocks(masks.astype(np.float32), f)
        if SHADING_SCALE_MM:                                   # on the blocks: the same smooth mean, a quarter of the work
            images = images / shading(images, masks, (s.pixel_mm[0] * f[0], s.pixel_mm[1] * f[1]))
        return cls(images, ndimage.gaussian_filter(masks, (0.0, 1.0, 1.0)), f, (box[0].start, box[1].start))


def shading(images: NDArray[np.float32], masks: NDArray, pixel_mm: tuple[float, float]) -> NDArray[np.float32]:
    """The shading of each slice ``images [n, H, W]`` (scaled by their stack's median brain intensity)
    that the image term divides out: its local brain mean within :data:`SHADING_SCALE_MM` (a Gaussian
    average weighed by the brain ``masks``, 0..1), where that mean lies outside
    :data:`SHADING_RANGE`, by as much as it lies outside; 1 elsewhere.

    What N4 leaves of a dark ball (3 T dielectric shading) or a coil's falloff sits still in the
    scanner while the fetus moves, so two crossing slices see it at different places of the brain and
    their intensities disagree where their poses are right. A brain's own contrast varies its local
    mean too, but less: only what lies beyond that is taken out.

    Example (a slice whose left half is 0.5 x as bright: its shading there is about 0.63; the right is 1):
        >>> img = np.ones((1, 20, 40), np.float32); img[:, :, :20] = 0.5
        >>> s = shading(img, np.ones(img.shape, bool), (1.0, 1.0))
        >>> round(float(s[0, 10, 5]), 2), float(s[0, 10, 35])
        (0.63, 1.0)
    """
    sigma = (0.0, SHADING_SCALE_MM / pixel_mm[0], SHADING_SCALE_MM / pixel_mm[1])
    m = np.asarray(masks, np.float32)
    weight = ndimage.gaussian_filter(m, sigma, truncate=3.0)
    mean = ndimage.gaussian_filter(images * m, sigma, truncate=3.0) / np.maximum(weight, 1e-6)
    local = np.where(weight > 0.05, mean, 1.0)
    return np.maximum(local / np.clip(local, *SHADING_RANGE), 0.1).astype(np.float32)   # no blow-up of noise


class SampledStack:
    """A stack's smoothed, scaled images and masks, sampled at atlas points (bilinear)."""

    def __init__(self, s: StackImages, sigma_mm: float, blocked: BlockedStack | None = None) -> None:
        blocked = blocked or BlockedStack.of(s)
        images, f = blocked.images, blocked.factors
        h, w = s.images.shape[1:]
        r0, c0 = blocked.origin
        pixel = (s.pixel_mm[0] * f[0], s.pixel_mm[1] * f[1])
        self.images = ndimage.gaussian_filter(images, (0.0, sigma_mm / pixel[0], sigma_mm / pixel[1]))
        self.masks = blocked.masks
        pad = ((0, 0), (1, 1), (1, 1))                                      # a zero border: bilinear fades to 0
        self.images_flat = np.pad(self.images, pad).ravel()
        self.masks_flat = np.pad(self.masks, pad).ravel()
        self.gradient_flat = [np.pad(g, pad).ravel() for g in np.gradient(self.images, axis=(1, 2))]
        self.padded = (images.shape[1] + 2, images.shape[2] + 2)
        # block (r', c') is centred on the original pixel (r0 + f r' + (f - 1) / 2, ...)
        self.pixel_from_slice = np.array([[0.0, 1.0 / pixel[0], 0.0, ((h - 1) / 2.0 - r0 - (f[0] - 1) / 2.0) / f[0]],   # row
                                          [1.0 / pixel[1], 0.0, 0.0, ((w - 1) / 2.0 - c0 - (f[1] - 1) / 2.0) / f[1]]])  # column

    def line_pixels(self, slice_from_atlas: NDArray, line: NDArray) -> NDArray[np.float64]:
        """``[M, 2, 2]`` (row, column) of two atlas points ``line`` ``[M, 2, 3]`` in slices whose
        ``slice_from_atlas`` are ``[M, 4, 4]``."""
        pixel_from_atlas = np.einsum("ij,mjk->mik", self.pixel_from_slice, slice_from_atlas)   # [M, 2, 4]
        return np.einsum("mij,mej->mei", pixel_from_atlas[:, :, :3], line) + pixel_from_atlas[:, None, :, 3]

    def sample(self, which: NDArray, rc: NDArray, masks: bool = False) -> NDArray[np.float32]:
        """Values of slices ``which`` ``[P]`` at pixels ``rc`` ``[P, 2]`` (bilinear; 0 beyond the
        image, fading over its border pixel)."""
        return self.sample_cells(self.cells(which, rc), masks)

    def sample_gradient(self, which: NDArray, rc: NDArray) -> NDArray[np.float32]:
        """``[P, 2]`` the smoothed image's derivatives along rows and columns (per pixel) there."""
        return self.gradient_cells(self.cells(which, rc))

    def sample_cells(self, cells: tuple[NDArray, ...], masks: bool = False) -> NDArray[np.float32]:
        """:meth:`sample` at the :meth:`cells` of some points."""
        return self._bilinear(self.masks_flat if masks else self.images_flat, *cells)

    def gradient_cells(self, cells: tuple[NDArray, ...]) -> NDArray[np.float32]:
        """:meth:`sample_gradient` at the :meth:`cells` of some points."""
        return np.stack([self._bilinear(g, *cells) for g in self.gradient_flat], axis=1)

    def cells(self, which: NDArray, rc: NDArray) -> tuple[NDArray, ...]:
        """Where points fall among the pixels: the flat index of each one's top-left pixel, its
        fractions along rows and columns, and whether it lies inside the image."""
        h, w = self.padded
        r, c = rc[:, 0] + 1.0, rc[:, 1] + 1.0
        inside = (r >= 0) & (r < h - 1) & (c >= 0) & (c < w - 1)
        r, c = np.clip(r, 0, h - 1.001), np.clip(c, 0, w - 1.001)
        r0, c0 = r.astype(np.int64), c.astype(np.int64)
        fr, fc = (r - r0).astype(np.float32), (c - c0).astype(np.float32)
        return which.astype(np.int64) * (h * w) + r0 * w + c0, fr, fc, inside

    def _bilinear(self, flat: NDArray, i: NDArray, fr: NDArray, fc: NDArray, inside: NDArray) -> NDArray[np.float32]:
        w = self.padded[1]
        top = flat[i] + fc * (flat[i + 1] - flat[i])
        bottom = flat[i + w] + fc * (flat[i + w + 1] - flat[i + w])
        return np.where(inside, top + fr * (bottom - top), 0.0).astype(np.float32)


def _blocks(images: NDArray, f: tuple[int, int]) -> NDArray[np.float32]:
    """``[n, H, W]`` averaged over ``f[0] x f[1]`` pixel blocks (the rows and columns past the last
    whole block dropped).

    Example:
        >>> _blocks(np.arange(12.0).reshape(1, 3, 4), (2, 2)).tolist()
        [[[2.5, 4.5]]]
    """
    if f == (1, 1):
        return images
    n, h, w = images.shape
    whole = images[:, :h // f[0] * f[0], :w // f[1] * f[1]]
    total = sum(whole[:, i::f[0], j::f[1]].astype(np.float32) for i in range(f[0]) for j in range(f[1]))
    return (total / (f[0] * f[1])).astype(np.float32)


class ImageTerm:
    """The image residuals of one pass: both slices' values at the chosen points of each pair's line."""

    def __init__(self, sampled: list[SampledStack], stack_of: NDArray, local: NDArray, pairs: NDArray, t: NDArray) -> None:
        self.sampled, self.stack_of, self.local, self.pairs, self.t = sampled, stack_of, local, pairs, t
        self.pair_of = np.repeat(np.arange(len(pairs)), len(t))
        self.t_of = np.tile(np.arange(len(t)), len(pairs))
        self.sw = np.ones(len(self.pair_of))
        self._index()

    def select(self, w: NDArray, min_weight: float, max_points: int | None = None) -> None:
        """Keep the points of pairs whose lines cross both brains over ``min_weight`` points' worth,
        where both masks are (nearly) nonzero, at most ``max_points`` (default :data:`MAX_POINTS`;
        whole lines); weights fixed from here on."""
        max_points = MAX_POINTS if max_points is None else max_points
        total = np.bincount(self.pair_of, weights=w, minlength=len(self.pairs))
        keep = (w > 1e-3) & (total[self.pair_of] >= min_weight)
        count = np.bincount(self.pair_of[keep], minlength=len(self.pairs))
        if count.sum() > max_points:               # many stacks: a fixed random share of the pairs, whole lines
            order = np.random.default_rng(0).permutation(len(self.pairs))
            chosen = np.zeros(len(self.pairs), bool)
            chosen[order[np.cumsum(count[order]) <= max_points]] = True
            keep &= chosen[self.pair_of]
        used, pair_of = np.unique(self.pair_of[keep], return_inverse=True)
        self.pairs, self.pair_of, self.t_of, self.sw = self.pairs[used], pair_of, self.t_of[keep], np.sqrt(w[keep])
        self._index()

    def _index(self) -> None:
        """Per (role, stack): the pairs whose slice in that role is of that stack, and their points
        (what :meth:`values` gathers, worked out once per point set)."""
        self._last = None
        self.groups = []
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

    def _where(self, atlas_from_slice: NDArray) -> tuple[NDArray, list[tuple]]:
        """Each pair's line (its base point and the point 1 mm along it, ``[M, 2, 3]``) and, per
        (role, stack) group: the stack, the group's rows, their slices (global) and where their
        points fall among those slices' pixels (:meth:`SampledStack.cells`). The last poses' answer
        is kept: the Jacobian at a pose set follows the residuals at the same poses."""
        if self._last is not None and np.array_equal(self._last[0], atlas_from_slice):
            return self._last[1], self._last[2]
        line = pair_points(atlas_from_slice, atlas_from_slice, self.pairs, np.array([0.0, 1.0]))   # base, base + d
        inv = se3.inverse(atlas_from_slice)
        sites = []
        for role, s, mine, g, rows, pos, k, t in self.groups:
            st = self.sampled[s]
            ends = st.line_pixels(inv[g], line[mine])[pos]                         # [P_s, 2, 2]
            sites.append((role, st, rows, g[pos], st.cells(k, ends[:, 0] + t * (ends[:, 1] - ends[:, 0]))))
        self._last = (np.array(atlas_from_slice, copy=True), line, sites)
        return line, sites

    def points(self, atlas_from_slice: NDArray) -> NDArray[np.float64]:
        """``[P, 3]`` each point in the atlas."""
        line = self._where(atlas_from_slice)[0][self.pair_of]
        return line[:, 0] + self.t[self.t_of][:, None] * (line[:, 1] - line[:, 0])

    def values(self, atlas_from_slice: NDArray, masks: bool = False) -> NDArray[np.float32]:
        """``[2, P]`` both slices' values at each point (images, or masks)."""
        out = np.zeros((2, len(self.pair_of)), np.float32)
        for role, st, rows, _, cells in self._where(atlas_from_slice)[1]:
            out[role, rows] = st.sample_cells(cells, masks)
        return out

    def gradients(self, atlas_from_slice: NDArray) -> NDArray[np.float64]:
        """``[2, P, 3]`` both slices' image gradients at each point (per atlas mm, in each slice's
        plane): what the residuals' derivatives need besides the geometry."""
        grad = np.zeros((2, len(self.pair_of), 3))
        for role, st, rows, slices, cells in self._where(atlas_from_slice)[1]:
            gp = st.gradient_cells(cells)                                         # per pixel (row, col)
            in_plane = gp[:, :1] * st.pixel_from_slice[0, :3] + gp[:, 1:] * st.pixel_from_slice[1, :3]
            grad[role, rows] = np.einsum("pij,pj->pi", atlas_from_slice[slices, :3, :3], in_plane)
        return grad

    def residuals(self, atlas_from_slice: NDArray) -> NDArray[np.float64]:
        va, vb = self.values(atlas_from_slice)
        return self.sw * (va.astype(np.float64) - vb)
