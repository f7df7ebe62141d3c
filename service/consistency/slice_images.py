"""A request's slices as the image term samples them: scaled, cut to the brain, smoothed, side by side.

Each stack's images are scaled by its median brain intensity, freed of the shading N4 leaves, averaged
over blocks of about 1 mm and cut to its brain's box (:class:`BlockedStack`, once per request), then
smoothed in-plane for each pass of :func:`~service.consistency.image_refinement.refine`
(:class:`SampledStack`). A pass's stacks are sampled together (:class:`SampledStacks`): their flat
arrays side by side, so that the points of every slice of every stack are found and read in one
set of array operations.

Example (two stacks of one 4 x 4 slice each; the second slice's centre pixel, bilinear):
    >>> img = np.arange(32, dtype=np.float32).reshape(2, 1, 4, 4) + 1
    >>> stacks = [SampledStack(StackImages(i, np.ones((1, 4, 4), bool), (1.0, 1.0), np.eye(4)[None],
    ...                                    np.ones(1, bool)), 0.0) for i in img]
    >>> both = SampledStacks(stacks)
    >>> cells = both.cells(np.array([1]), np.array([0]), np.array([[1.5, 1.5]]))
    >>> both.sample(both.images, cells).round(3).tolist()       # the stack's 17..32 scaled by its median 24.5
    [1.0]
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from service.core.threads import two_threads
from service.geometry.frames import voxels_covering


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


SHADING_SCALE_MM = 6.0
"""The in-plane reach (Gaussian sigma, mm) of a slice's local brain mean (:func:`shading`); None: no
shading correction."""
BLOCK_SIGMA_PX = 2.0
"""A Gaussian whose sigma spans this many blocks of 2 x 2 pixels or more (the shading's local mean, the
coarsest pass's smoothing; a finer pass's on pixels finer than 0.75 mm) is applied on the blocks and
brought back linearly (:func:`_wide_gaussian`): an image smoothed over 4.5 or 6 mm is as smooth on
2 mm blocks as on 1 mm pixels, at a quarter of the work. Blocks of 3 pixels or more would leave a
ripple of their period: bringing them back blurs the pixels between their centres more than those
on them."""
SHADING_RANGE = (0.8, 1.25)
"""The local brain mean, over the stack's median, that counts as anatomy (:func:`shading`): on
noise-free atlas brains at their true poses the refinement then moves the slices no further than
without the correction (docs/reports/consistency-experiments.md)."""
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
    support: NDArray[np.float64] = field(init=False)
    """``[n, 2, 2]`` each slice's box of nonzero ``masks`` (:func:`_support_boxes`)."""
    fingerprints: NDArray[np.uint64] = field(init=False)
    """``[n]`` a checksum of each slice's ``masks``: the slice's name in the point budget's order
    (:func:`~service.consistency.intersections.slice_keys`), whatever its stack's place in the
    request and its own place in the stack. Of the masks, not the images: a file written again (its
    affine's rounding, another reader) changes the images' last bits, and the choice of crossing
    lines would change with them."""

    def __post_init__(self) -> None:
        self.support = _support_boxes(self.masks)
        self.fingerprints = np.array([zlib.crc32(np.ascontiguousarray(m).view(np.uint8)) for m in self.masks], np.uint64)

    @classmethod
    def of(cls, s: StackImages) -> "BlockedStack":
        brain = s.images[s.masks]
        scale = float(np.median(brain)) if brain.size else 1.0
        scale = scale if np.isfinite(scale) and scale > 0 else 1.0     # the units' own size, however small
        f = (max(1, round(1.0 / s.pixel_mm[0])), max(1, round(1.0 / s.pixel_mm[1])))
        h, w = s.images.shape[1:]
        box = [slice(0, h), slice(0, w)]
        found = s.masks.any(axis=0)
        if found.any():
            for axis in (0, 1):
                hit = np.flatnonzero(found.any(axis=1 - axis))
                margin = int(voxels_covering(CROP_MARGIN_MM, s.pixel_mm[axis]))
                lo = int(max(hit[0] - margin, 0) // f[axis] * f[axis])
                box[axis] = slice(lo, int(min(hit[-1] + margin + 1, (h, w)[axis])))
        images, masks = s.images[:, box[0], box[1]], s.masks[:, box[0], box[1]]
        images = _blocks(images.astype(np.float32) / np.float32(scale), f)
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
    f, sigma = _block_factors(SHADING_SCALE_MM, pixel_mm, images.shape[1:])
    m = np.asarray(masks, np.float32)
    weight = ndimage.gaussian_filter(_blocks(m, f), sigma, truncate=3.0)
    mean = ndimage.gaussian_filter(_blocks(images * m, f), sigma, truncate=3.0) / np.maximum(weight, 1e-6)
    local = np.where(weight > 0.05, mean, 1.0)
    factor = np.maximum(local / np.clip(local, *SHADING_RANGE), 0.1)    # no blow-up of noise
    return _unblock(factor, f, images.shape[1:])


def _block_factors(sigma_mm: float, pixel_mm: tuple[float, float], shape: tuple[int, ...],
                   ) -> tuple[tuple[int, int], tuple[float, float, float]]:
    """The blocks a Gaussian of ``sigma_mm`` is applied on along each axis (2 pixels where its sigma
    spans :data:`BLOCK_SIGMA_PX` blocks or more and the image of ``shape`` pixels has 4 or more, else 1)
    and its sigma there (slice axis, rows, columns; in blocks). Averaging 2 pixels into a block
    blurs by a variance of 1/4 pixel^2 and bringing the blocks back linearly by 3/4 (every pixel lies
    a quarter of the way from a block's centre to the next): the Gaussian on the blocks is narrower by
    as much, so that the three together are the Gaussian on the pixels (to 0.3 % of the image's
    contrast at 4.5 mm on 1.1 mm pixels, 2.2 % without the correction).

    Example (6 mm on 1 mm pixels: blocks of 2, and 2.96 blocks rather than 3):
        >>> f, sigma = _block_factors(6.0, (1.0, 1.0), (100, 100))
        >>> f, round(float(sigma[1]), 2)
        ((2, 2), 2.96)
    """
    f = tuple(2 if sigma_mm / p >= 2 * BLOCK_SIGMA_PX and n >= 4 else 1 for p, n in zip(pixel_mm, shape))
    px = [sigma_mm / p for p in pixel_mm]
    return f, (0.0, *(np.sqrt(s ** 2 - (1.0 if k == 2 else 0.0)) / k for s, k in zip(px, f)))


def _wide_gaussian(images: NDArray[np.float32], sigma_mm: float, pixel_mm: tuple[float, float]) -> NDArray[np.float32]:
    """``images [n, H, W]`` smoothed in-plane by a Gaussian of ``sigma_mm``: on blocks where it is wide
    (:func:`_block_factors`), on the pixels otherwise."""
    f, sigma = _block_factors(sigma_mm, pixel_mm, images.shape[1:])
    if f == (1, 1):
        return ndimage.gaussian_filter(images, sigma)
    return _unblock(ndimage.gaussian_filter(_blocks(images, f), sigma), f, images.shape[1:])


def _unblock(blocks: NDArray, f: tuple[int, int], shape: tuple[int, int]) -> NDArray[np.float32]:
    """``[n, h, w]`` block values back on the ``shape`` pixels they were averaged from (:func:`_blocks`):
    linear between the blocks' centres, the nearest block beyond them and over the rows and columns
    past the last whole block.

    Example:
        >>> _unblock(np.array([[[1.0, 3.0]]]), (1, 2), (1, 5)).tolist()
        [[[1.0, 1.5, 2.5, 3.0, 3.0]]]
    """
    out = np.asarray(blocks, np.float32)
    if tuple(f) == (1, 1):                                   # no blocks: the pixels themselves
        return out
    for axis, (factor, size) in enumerate(zip(f, shape), start=1):
        at = np.clip((np.arange(size) + 0.5) / factor - 0.5, 0.0, out.shape[axis] - 1)
        lo = np.floor(at).astype(np.int64)
        hi = np.minimum(lo + 1, out.shape[axis] - 1)
        frac = np.expand_dims((at - lo).astype(np.float32), tuple(a for a in range(out.ndim) if a != axis))
        low = np.take(out, lo, axis=axis)
        out = low + frac * (np.take(out, hi, axis=axis) - low)
    return out


class SampledStack:
    """A stack's smoothed, scaled images and its masks as one pass samples them (:class:`SampledStacks`)."""

    def __init__(self, s: StackImages, sigma_mm: float, blocked: BlockedStack | None = None) -> None:
        blocked = blocked or BlockedStack.of(s)
        images, f = blocked.images, blocked.factors
        h, w = s.images.shape[1:]
        r0, c0 = blocked.origin
        pixel = (s.pixel_mm[0] * f[0], s.pixel_mm[1] * f[1])
        self.images = _wide_gaussian(images, sigma_mm, pixel)
        self.masks = blocked.masks
        self.fingerprints = blocked.fingerprints
        self.support = blocked.support
        self.padded = (images.shape[1] + 2, images.shape[2] + 2)                # a zero border: bilinear fades to 0
        # block (r', c') is centred on the original pixel (r0 + f r' + (f - 1) / 2, ...)
        self.pixel_from_slice = np.array([[0.0, 1.0 / pixel[0], 0.0, ((h - 1) / 2.0 - r0 - (f[0] - 1) / 2.0) / f[0]],   # row
                                          [1.0 / pixel[1], 0.0, 0.0, ((w - 1) / 2.0 - c0 - (f[1] - 1) / 2.0) / f[1]]])  # column


def _support_boxes(masks: NDArray) -> NDArray[np.float64]:
    """``[n, 2, 2]`` each slice's box of nonzero ``masks [n, H, W]`` pixels, ``[[row_lo, row_hi],
    [col_lo, col_hi]]`` (an empty slice's box is empty: lo > hi).

    Example:
        >>> m = np.zeros((2, 5, 6)); m[0, 1:3, 2:5] = 0.5
        >>> _support_boxes(m).tolist()
        [[[1.0, 2.0], [2.0, 4.0]], [[inf, -inf], [inf, -inf]]]
    """
    out = np.empty((len(masks), 2, 2))
    for axis, along in ((0, 2), (1, 1)):
        hit = (masks != 0).any(axis=along)                                     # [n, H] rows, [n, W] columns
        size = hit.shape[1]
        lo, hi = np.argmax(hit, axis=1), size - 1 - np.argmax(hit[:, ::-1], axis=1)
        found = hit.any(axis=1)
        out[:, axis, 0] = np.where(found, lo, np.inf)
        out[:, axis, 1] = np.where(found, hi, -np.inf)
    return out


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


class Cells(NamedTuple):
    """Where points fall among the pixels of :class:`SampledStacks`' flat arrays: the flat index of
    each one's top-left pixel and of the pixel below it, its fractions along rows and columns, and
    whether it lies inside its image."""

    index: NDArray[np.int64]
    below: NDArray[np.int64]
    fr: NDArray[np.float32]
    fc: NDArray[np.float32]
    inside: NDArray[np.bool_]


class SampledStacks:
    """A pass's stacks (:class:`SampledStack`) side by side in flat arrays, sampled at the pixels of
    any of their slices at once (bilinear; 0 beyond an image, fading over its border pixel).

    Attributes:
        images, masks, gradient_rows, gradient_cols: the stacks' flat arrays, one after the other.
        pixel_from_slice: ``[S, 2, 4]`` each stack's slice mm -> (row, column) of its blocks.
        support: ``[N, 2, 2]`` each slice's mask box (:func:`_support_boxes`), the slices of the
            stacks in turn.
        first_slice: ``[S]`` each stack's first slice among them.
    """

    def __init__(self, stacks: list[SampledStack]) -> None:
        shapes = [(len(s.images), *s.padded) for s in stacks]
        sizes = [n * h * w for n, h, w in shapes]
        self.padded = np.array([s.padded for s in stacks], np.int64)              # [S, 2]
        self.base = np.cumsum([0] + sizes[:-1])                                  # each stack's first value
        self.pixel_from_slice = np.stack([s.pixel_from_slice for s in stacks])
        self.support = np.concatenate([s.support for s in stacks])
        self.first_slice = np.cumsum([0] + [len(s.images) for s in stacks[:-1]])
        self.images, self.masks, self.gradient_rows, self.gradient_cols = (np.empty(sum(sizes), np.float32)
                                                                            for _ in range(4))

        def fill(half: int) -> None:                                             # every other stack, one a thread
            for i in range(half, len(stacks), 2):
                part = lambda flat: flat[self.base[i]:self.base[i] + sizes[i]].reshape(shapes[i])  # noqa: E731
                _pad_into(part(self.images), stacks[i].images)
                _pad_into(part(self.masks), stacks[i].masks)
                _gradients_into(part(self.gradient_rows), part(self.gradient_cols), stacks[i].images)

        two_threads(fill)

    def layout(self, stack: NDArray, local: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """Where slices ``local [P]`` of stacks ``stack [P]`` start in the flat arrays, and their padded
        heights and widths."""
        h, w = self.padded[stack, 0], self.padded[stack, 1]
        return self.base[stack] + local * (h * w), h, w

    def cells(self, stack: NDArray, local: NDArray, rc: NDArray) -> Cells:
        """The :class:`Cells` of points at pixels ``rc [P, 2]`` (row, column) of slices ``local [P]``
        of stacks ``stack [P]``."""
        return self.cells_from(*self.layout(stack, local), rc[:, 0], rc[:, 1])

    @staticmethod
    def cells_from(start: NDArray, h: NDArray, w: NDArray, rows: NDArray, cols: NDArray) -> Cells:
        """:meth:`cells` of points at pixels ``(rows, cols)`` of slices laid out as :meth:`layout`
        gives (a caller that samples the same slices again keeps that)."""
        r, c = rows + 1.0, cols + 1.0
        inside = (r >= 0) & (r < h - 1) & (c >= 0) & (c < w - 1)
        r, c = np.clip(r, 0, h - 1.001), np.clip(c, 0, w - 1.001)
        r0, c0 = r.astype(np.int64), c.astype(np.int64)
        index = start + r0 * w + c0
        return Cells(index, index + w, (r - r0).astype(np.float32), (c - c0).astype(np.float32), inside)

    @staticmethod
    def sample(flat: NDArray, cells: Cells) -> NDArray[np.float32]:
        """``[P]`` the values of one of the flat arrays (``images``, ``masks``, a gradient) at ``cells``."""
        i, b = cells.index, cells.below
        top = flat[i] + cells.fc * (flat[i + 1] - flat[i])
        bottom = flat[b] + cells.fc * (flat[b + 1] - flat[b])
        return np.where(cells.inside, top + cells.fr * (bottom - top), 0.0).astype(np.float32)


def _pad_into(out: NDArray, images: NDArray) -> None:
    """``images [n, h, w]`` into ``out [n, h + 2, w + 2]`` with a border of zeros."""
    _zero_border(out)
    out[:, 1:-1, 1:-1] = images


def _zero_border(out: NDArray) -> None:
    out[:, 0], out[:, -1], out[:, :, 0], out[:, :, -1] = 0, 0, 0, 0


def _gradients_into(rows: NDArray, cols: NDArray, images: NDArray) -> None:
    """``np.gradient(images, axis=(1, 2))`` (central differences, one-sided at the edges) into ``rows``
    and ``cols`` ``[n, h + 2, w + 2]`` with a border of zeros, made in place.

    Example:
        >>> img = np.arange(12, dtype=np.float32).reshape(1, 3, 4) ** 2
        >>> rows, cols = np.empty((2, 1, 5, 6), np.float32)
        >>> _gradients_into(rows, cols, img)
        >>> expected = np.gradient(img, axis=(1, 2))
        >>> bool(np.array_equal(rows[:, 1:-1, 1:-1], expected[0]) and np.array_equal(cols[:, 1:-1, 1:-1], expected[1]))
        True
    """
    for out, axis in ((rows, 1), (cols, 2)):
        _zero_border(out)
        f = np.moveaxis(images, axis, 1)
        g = np.moveaxis(out[:, 1:-1, 1:-1], axis, 1)
        if f.shape[1] < 2:                                                       # no neighbour to differ from
            g[...] = 0
            continue
        np.subtract(f[:, 2:], f[:, :-2], out=g[:, 1:-1])
        g[:, 1:-1] /= 2.0
        np.subtract(f[:, 1], f[:, 0], out=g[:, 0])
        np.subtract(f[:, -1], f[:, -2], out=g[:, -1])
