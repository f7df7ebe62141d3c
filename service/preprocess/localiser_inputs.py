"""THE localiser's input: what the brain-localisation network sees, shared by the service and training.

For a stack (any orientation, any in-plane pixel size, whole uterus or cropped), in order:

1. split it into slices along its slice axis, each laid out as a picture by the scanner's axes
   (:func:`~service.preprocess.stack.slice_images`): however the file stores its in-plane voxels,
   the network sees the same pictures and the mask is the same;
2. scale intensities by the stack's 99.5th percentile (over pixels out of step with its rows and
   columns, :func:`intensity_scale`; clipped to 0..2), so that no scanner's units matter;
3. resample every slice to square pixels of ``grid_mm`` (the model's; Gaussian anti-aliasing first,
   so a 0.5 mm and a 1.5 mm acquisition look alike), its field of view kept;
4. continue the image by a band of fluid (:data:`FLUID_BAND_MM` at :data:`FLUID_LEVEL`) beyond
   each side where it ends in tissue, not in the air around the mother (:func:`open_sides`: a stack
   cropped close to the head, a head at the image's edge), then pad with zeros to a multiple of
   :data:`PAD_MULTIPLE` on each side, and to at least :data:`MIN_GRID_PX`, centred;
5. stack each slice with its two neighbours along the slice axis as three channels (2.5D; the end
   slices repeat themselves).

:meth:`LocaliserGrid.to_stack` maps the network's per-pixel output back onto the stack's own grid, and
:func:`target_maps` a mask of the stack onto the network's grid.

Example:
    >>> import numpy as np
    >>> from service.io.volume import Volume
    >>> body = np.pad(np.random.default_rng(0).random((90, 70, 6), np.float32), ((5, 5), (5, 5), (0, 0)))
    >>> vol = Volume(body, np.diag([1.25, 1.25, 3.0, 1.0]))         # a field of view that ends in air
    >>> x, grid = localiser_inputs(vol, grid_mm=2.5)
    >>> x.shape                                       # 6 slices, 3 channels, 40 x 50 px padded to 64
    (6, 3, 64, 64)
    >>> float(x[0, 1, grid.offset[0], grid.offset[1] - 1])          # zeros beyond the air
    0.0
    >>> grid.to_stack(x[:, 1]).shape == vol.array.shape
    True
    >>> x, grid = localiser_inputs(Volume(body[5:-5, 5:-5], vol.affine), 2.5)   # cropped to the body
    >>> round(float(x[0, 1, grid.offset[0], grid.offset[1] - 1]), 2)             # a band of fluid beyond it
    0.4
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage, sparse

from service.core.errors import PayloadTooLarge
from service.geometry.sampling import FWHM_TO_SIGMA, linear_operator
from service.io.volume import Volume
from service.preprocess.stack import pictures, slice_images, stack_axis

PAD_MULTIPLE = 16
MIN_GRID_PX = 64
"""Slices are padded to at least this many grid pixels a side (160 mm at 2.5 mm): a stack cropped to
the head before it is sent keeps the canvas the network learnt on (fields of view of 130-400 mm),
which it needs to see the head's poles; every field of view of the training scenes is padded
to this size or more anyway."""
PERCENTILE = 99.5
SIDES = ("top", "bottom", "left", "right")
"""A slice's sides: its first and last rows, its first and last columns."""
OPEN_SIDE_LEVEL = 0.1
OPEN_SIDE_SHARE = 0.5
"""A side of a stack is open where over this share of its edge pixels (every slice's) are brighter
than :data:`OPEN_SIDE_LEVEL` of the stack's bright end: the image ends in tissue or fluid. A
whole-uterus field of view ends in the air around the mother on every side."""
FLUID_BAND_MM = 20.0
FLUID_LEVEL = 0.4
"""The band beyond an open side (of the bright end: fluid-bright). A brain that runs into zeros is
unlike any head the network learnt: it finds part of it, or none. Against a bright band it sees a
brain bounded all round, as fluid and CSF bound every head it learnt (docs/reports/localiser-
experiments.md, "A head at the edge of the image")."""

SEARCH_GRID_MM = 2.5
MAX_SEARCH_MEGAPIXELS = 40.0
"""The most pixels (millions, at a grid of :data:`SEARCH_GRID_MM`: each slice's field of view in such
pixels, padded as :data:`MIN_GRID_PX` pads it) one request may ask the localiser to search, over
its stacks without a brain mask: its network's cost grows with the field of view in mm, not with
the bytes a file holds, so a small file of coarse pixels over a field of view no fetus fills would
hold both processing slots for minutes. A scanner's six whole-uterus stacks ask a tenth of it."""


def search_megapixels(volume: Volume, grid_mm: float = SEARCH_GRID_MM) -> float:
    """The pixels (millions) the localiser searches in ``volume``: its slices times each slice's field of
    view in pixels of ``grid_mm``, at least :data:`MIN_GRID_PX` a side (before the fluid band and the
    padding to :data:`PAD_MULTIPLE`, which add little).

    Example (22 slices of 320 x 320 pixels of 1.125 mm: 144 x 144 pixels of 2.5 mm each):
        >>> round(search_megapixels(Volume(np.zeros((320, 320, 22), np.float32), np.diag([1.125, 1.125, 3.3, 1.0]))), 3)
        0.456
    """
    axis = stack_axis(volume)
    sides = [max(math.ceil(volume.array.shape[k] * float(volume.spacing[k]) / grid_mm - 1e-6), MIN_GRID_PX)
             for k in range(3) if k != axis]
    return volume.array.shape[axis] * sides[0] * sides[1] / 1e6


def check_search(stacks: list[tuple[str, Volume]]) -> None:
    """413 naming the stacks where those the localiser is to search (``(name, volume)``: each stack sent
    without a mask or with a region of interest) ask it for more than :data:`MAX_SEARCH_MEGAPIXELS`.

    Example (three stacks of 99 slices over a field of view of 1 m, 10 mm pixels):
        >>> wide = Volume(np.zeros((100, 100, 99), np.float32), np.diag([10.0, 10.0, 11.0, 1.0]))
        >>> check_search([("a.nii", wide)] * 2)
        >>> try:
        ...     check_search([("a.nii", wide), ("b.nii", wide), ("c.nii", wide)])
        ... except PayloadTooLarge as exc:
        ...     print(exc.status, str(exc)[:92])
        413 stacks a.nii, b.nii, c.nii: the localiser would search 47.5 million pixels of 2.5 mm in them
    """
    sizes = [(name, search_megapixels(volume)) for name, volume in stacks]
    asked = sum(mp for _, mp in sizes)
    if asked > MAX_SEARCH_MEGAPIXELS:
        widest = max(float(v.array.shape[k] * v.spacing[k]) for _, v in stacks for k in range(3) if k != stack_axis(v))
        names = ", ".join(n for n, _ in sizes)
        raise PayloadTooLarge(f"stacks {names}: the localiser would search {asked:.1f} million pixels of "
                              f"{SEARCH_GRID_MM:g} mm in them (fields of view of up to {widest:.0f} mm), over its "
                              f"{MAX_SEARCH_MEGAPIXELS:g} a request: send their brain masks, stacks cropped to the "
                              "uterus, or fewer stacks a request")


@dataclass(frozen=True)
class LocaliserGrid:
    """How the network's grid sits on the stack: slice axis, resampled and padded sizes."""

    shape: tuple[int, int, int]             # the stack's array shape
    slice_axis: int
    layout: tuple[int, int, int, int]       # how each slice is laid out as a picture (frames.in_plane_layout)
    native: tuple[int, int]                 # (H, W) of a slice's picture at the stack's pixels
    resampled: tuple[int, int]              # (h, w) on the network grid, before padding
    offset: tuple[int, int]                 # where the resampled slice starts in the padded one
    grid_mm: float                          # the grid's pixel size
    band: tuple[int, int, int, int] = (0, 0, 0, 0)   # fluid band pixels beyond each of SIDES (step 4)

    def to_stack(self, maps: NDArray) -> NDArray[np.float32]:
        """Per-slice maps ``[n, Hp, Wp]`` on the padded network grid -> the stack's array shape (bilinear,
        pixel areas aligned as :func:`scipy.ndimage.zoom` with ``grid_mode`` aligns them; ``nearest``
        beyond the edges). Only the native pixels near the maps' non-zero box are interpolated; the
        rest are 0."""
        r, c = self.offset
        h, w = self.resampled
        core = np.asarray(maps, np.float32)[:, r:r + h, c:c + w]
        out = np.zeros(self.shape, np.float32)                        # the stack's voxel order
        native = pictures(out, self.slice_axis, self.layout)          # a view of it, laid out as the maps
        nonzero = np.argwhere(core.any(axis=0))
        if len(nonzero) == 0:
            return out
        scale = np.array(self.native) / np.array([h, w])             # native pixels per network pixel
        lo = np.maximum(np.floor((nonzero.min(0) - 1) * scale).astype(int), 0)
        hi = np.minimum(np.ceil((nonzero.max(0) + 2) * scale).astype(int), self.native)
        rows = linear_operator((np.arange(lo[0], hi[0]) + 0.5) / scale[0] - 0.5, h)
        cols = linear_operator((np.arange(lo[1], hi[1]) + 0.5) / scale[1] - 0.5, w)
        native[:, lo[0]:hi[0], lo[1]:hi[1]] = _separable(np.ascontiguousarray(core), rows, cols)
        return out


def _separable(images: NDArray[np.float32], rows: sparse.csr_matrix, cols: sparse.csr_matrix) -> NDArray[np.float32]:
    """``rows @ image @ cols.T`` for every slice of ``images [n, H, W]`` (two sparse products)."""
    n, h_in, w_in = images.shape
    h, w = rows.shape[0], cols.shape[0]
    by_rows = rows @ np.ascontiguousarray(images.transpose(1, 0, 2)).reshape(h_in, n * w_in)      # [h, n*W]
    by_cols = np.ascontiguousarray(np.asarray(by_rows).reshape(h, n, w_in).transpose(2, 1, 0)).reshape(w_in, n * h)
    return np.ascontiguousarray(np.asarray(cols @ by_cols).reshape(w, n, h).transpose(1, 2, 0), dtype=np.float32)


@functools.lru_cache(maxsize=64)
def axis_operator(n_in: int, factor: float) -> sparse.csr_matrix:
    """The resampling of one image axis of ``n_in`` pixels by ``factor`` (< 1: shrinking) as a sparse
    ``[n_out, n_in]`` matrix: Gaussian anti-aliasing (where it shrinks; ``nearest`` edges) then
    linear interpolation with pixel areas aligned (:func:`scipy.ndimage.zoom`, ``grid_mode``).

    Both steps are linear and separable, so the matrix is made by applying them to the identity, and
    a slice is resampled as ``rows @ image @ cols.T``: the same numbers as filtering and zooming the
    image, at a few multiply-adds per output pixel.

    Example (a 100-pixel axis of 1.25 mm pixels onto 2.5 mm: 50 rows, each summing to 1):
        >>> m = axis_operator(100, 0.5)
        >>> m.shape, bool(np.allclose(m.sum(axis=1), 1.0))
        ((50, 100), True)
    """
    sigma = FWHM_TO_SIGMA * np.sqrt(max(1.0 / factor ** 2 - 1.0, 0.0))
    size = max(1, int(np.round(n_in * factor)))
    eye = np.eye(n_in)
    if sigma > 0:
        eye = ndimage.gaussian_filter1d(eye, sigma, axis=0, mode="nearest", truncate=3.0)
    dense = ndimage.zoom(eye, (size / n_in, 1.0), order=1, mode="nearest", grid_mode=True)
    dense[np.abs(dense) < 1e-9] = 0.0
    return sparse.csr_matrix(dense.astype(np.float32))


def _resample(images: NDArray[np.float32], pixel_mm: tuple[float, float], grid_mm: float) -> NDArray[np.float32]:
    """Slices ``[n, H, W]`` to square ``grid_mm`` pixels over the same field of view (bilinear, Gaussian
    anti-aliasing first where the grid is coarser): :func:`axis_operator` along rows, then columns."""
    _, h_in, w_in = images.shape
    return _separable(images, axis_operator(h_in, float(pixel_mm[0]) / grid_mm),
                      axis_operator(w_in, float(pixel_mm[1]) / grid_mm))


def open_sides(images: NDArray[np.float32]) -> frozenset[str]:
    """The :data:`SIDES` of slices ``[n, H, W]`` (scaled to their bright end) that end in tissue.

    Example (a head cropped close on its left: that side is open, the others end in air):
        >>> images = np.zeros((3, 40, 40), np.float32); images[:, 5:35, 0:25] = 0.6
        >>> sorted(open_sides(images))
        ['left']
    """
    ends = {"top": images[:, 0], "bottom": images[:, -1], "left": images[:, :, 0], "right": images[:, :, -1]}
    return frozenset(side for side, px in ends.items() if float((px > OPEN_SIDE_LEVEL).mean()) > OPEN_SIDE_SHARE)


def _pad(small: NDArray[np.float32], band: tuple[int, int, int, int] = (0, 0, 0, 0), fill: float = 0.0,
         ) -> tuple[NDArray[np.float32], tuple[int, int]]:
    """Zero-pad ``[n, h, w]`` to multiples of :data:`PAD_MULTIPLE` and at least :data:`MIN_GRID_PX`,
    centred, after a band of ``fill`` ``band`` pixels wide on each side (top, bottom, left, right);
    returns it and the offset of ``small`` in it.

    Example (a 4 x 4 slice with a 2-pixel band on its left: the band, then the slice):
        >>> padded, (r, c) = _pad(np.ones((1, 4, 4), np.float32), (0, 0, 2, 0), fill=0.5)
        >>> padded.shape, (r, c), padded[0, r, c - 3:c + 1].tolist()
        ((1, 64, 64), (30, 31), [0.0, 0.5, 0.5, 1.0])
    """
    h, w = small.shape[1:]
    top, bottom, left, right = band
    hb, wb = h + top + bottom, w + left + right
    hp, wp = (max(-(-n // PAD_MULTIPLE) * PAD_MULTIPLE, MIN_GRID_PX) for n in (hb, wb))
    r, c = (hp - hb) // 2, (wp - wb) // 2
    padded = np.zeros((len(small), hp, wp), np.float32)
    padded[:, r:r + hb, c:c + wb] = fill
    padded[:, r + top:r + top + h, c + left:c + left + w] = small
    return padded, (r + top, c + left)


def with_neighbours(slices: NDArray[np.float32]) -> NDArray[np.float32]:
    """``[n, H, W]`` -> ``[n, 3, H, W]``: each slice between its neighbours (ends repeat themselves)."""
    ext = np.concatenate([slices[:1], slices, slices[-1:]])
    return np.stack([ext[:-2], ext[1:-1], ext[2:]], axis=1)


def _band(images: NDArray[np.float32], grid_mm: float) -> tuple[int, int, int, int]:
    """Grid pixels of fluid band beyond each of the :data:`SIDES` (step 4)."""
    sides, width = open_sides(images), int(round(FLUID_BAND_MM / grid_mm))
    return tuple(width if side in sides else 0 for side in SIDES)


def intensity_scale(images: NDArray[np.float32]) -> float:
    """The :data:`PERCENTILE` th percentile of a stack's pixels ``[n, H, W]``, over every ``s``-th pixel
    of each slice in raster order, ``s`` the first step from 9 up that shares no factor with ``W``: as
    the whole stack's at a ninth of the cost, never in step with a row or a column, and the same
    pixels whichever order the slices are stored in. A grid of every third row and column would
    count a bright line (a zipper artefact, a saturated edge) three times or not at all: on one of
    its rows it sets the scale and leaves the stack black.

    Example (a saturated column on a row and column of the every-third grid):
        >>> images = np.random.default_rng(0).uniform(0, 100, (2, 320, 320)).astype(np.float32)
        >>> images[:, :, 201] = 65535.0
        >>> round(intensity_scale(images)), round(float(np.percentile(images[:, ::3, ::3], PERCENTILE)))
        (100, 65535)
    """
    height, width = images.shape[-2:]
    step = 9
    while math.gcd(step, width) != 1:
        step += 1
    raster = np.arange(0, height * width, step)          # picked where they lie: a view laid out by the
    return float(np.percentile(images[:, raster // width, raster % width], PERCENTILE))   # scanner is not copied


def localiser_inputs(volume: Volume, grid_mm: float) -> tuple[NDArray[np.float32], LocaliserGrid]:
    """The network inputs ``[n, 3, Hp, Wp]`` of a stack and the grid to map outputs back with."""
    axis = stack_axis(volume)
    images, pixel_mm, layout = slice_images(volume.array, volume.affine, axis)
    images = np.asarray(images, np.float32)
    finite = np.isfinite(images)
    if not finite.all():                                                  # NaN and inf pixels count as 0
        images = np.where(finite, images, np.float32(0.0))
    scale = intensity_scale(images)
    # float32 bounds: with Python floats numpy clips a float32 array through a buffered float64 loop, 5x slower
    images = np.clip(images / scale, np.float32(0.0), np.float32(2.0)) if scale > 0 else np.zeros_like(images)
    small = _resample(images, pixel_mm, grid_mm)
    band = _band(images, grid_mm)
    padded, offset = _pad(small, band, FLUID_LEVEL)
    x = with_neighbours(padded)
    grid = LocaliserGrid(tuple(volume.array.shape), axis, layout, images.shape[1:], small.shape[1:], offset, grid_mm,
                         band)
    return np.ascontiguousarray(x), grid


def target_maps(mask: NDArray, volume: Volume, grid: LocaliserGrid) -> NDArray[np.float32]:
    """A stack's brain mask on the network grid ``[n, Hp, Wp]`` (brain fraction per pixel): the
    training target that matches :func:`localiser_inputs` pixel for pixel, on the ``grid`` it
    returned for ``volume`` (no fluid in the band)."""
    images, pixel_mm, _ = slice_images(np.asarray(mask, np.float32), volume.affine, stack_axis(volume))
    return _pad(np.clip(_resample(images, pixel_mm, grid.grid_mm), 0.0, 1.0), grid.band)[0]
