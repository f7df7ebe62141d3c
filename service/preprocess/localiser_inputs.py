"""THE localiser's input: what the brain-localisation network sees, shared by the service and training.

For a stack (any orientation, any in-plane pixel size, whole uterus or cropped), in order:

1. split it into slices along its slice axis (:func:`~service.preprocess.stack.slice_images`);
2. scale intensities by the stack's 99.5th percentile (of every third pixel along rows and columns;
   clipped to 0..2), so that no scanner's units matter;
3. resample every slice to square pixels of ``grid_mm`` (the model's; Gaussian anti-aliasing first,
   so a 0.5 mm and a 1.5 mm acquisition look alike), its field of view kept;
4. pad with zeros to a multiple of :data:`PAD_MULTIPLE` on each side, and to at least
   :data:`MIN_GRID_PX`, centred;
5. stack each slice with its two neighbours along the slice axis as three channels (2.5D; the end
   slices repeat themselves).

:meth:`LocaliserGrid.to_stack` maps the network's per-pixel output back onto the stack's own grid.

Example:
    >>> import numpy as np
    >>> from service.io.volume import Volume
    >>> vol = Volume(np.random.default_rng(0).random((100, 80, 6), np.float32), np.diag([1.25, 1.25, 3.0, 1.0]))
    >>> x, grid = localiser_inputs(vol, grid_mm=2.5)
    >>> x.shape                                       # 6 slices, 3 channels, 40 x 50 px padded to 64
    (6, 3, 64, 64)
    >>> grid.to_stack(x[:, 1]).shape == vol.array.shape
    True
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage, sparse

from service.geometry.sampling import FWHM_TO_SIGMA, linear_operator
from service.io.volume import Volume
from service.preprocess.stack import slice_images, stack_axis, stack_from_slice_images

PAD_MULTIPLE = 16
MIN_GRID_PX = 64
"""Slices are padded to at least this many grid pixels a side (160 mm at 2.5 mm): a stack cropped to
the head before it is sent keeps the canvas the network learnt on (fields of view of 130-400 mm),
which it needs to see the head's poles; every field of view of the training scenes is padded
to this size or more anyway."""
PERCENTILE = 99.5


@dataclass(frozen=True)
class LocaliserGrid:
    """How the network's grid sits on the stack: slice axis, resampled and padded sizes."""

    shape: tuple[int, int, int]             # the stack's array shape
    slice_axis: int
    native: tuple[int, int]                 # (H, W) of a slice as stored
    resampled: tuple[int, int]              # (h, w) on the network grid, before padding
    offset: tuple[int, int]                 # where the resampled slice starts in the padded one

    def to_stack(self, maps: NDArray) -> NDArray[np.float32]:
        """Per-slice maps ``[n, Hp, Wp]`` on the padded network grid -> the stack's array shape (bilinear,
        pixel areas aligned as :func:`scipy.ndimage.zoom` with ``grid_mode`` aligns them; ``nearest``
        beyond the edges). Only the native pixels near the maps' non-zero box are interpolated; the
        rest are 0."""
        r, c = self.offset
        h, w = self.resampled
        core = np.asarray(maps, np.float32)[:, r:r + h, c:c + w]
        native = np.zeros((len(core), *self.native), np.float32)
        nonzero = np.argwhere(core.any(axis=0))
        if len(nonzero) == 0:
            return stack_from_slice_images(native, self.slice_axis)
        scale = np.array(self.native) / np.array([h, w])             # native pixels per network pixel
        lo = np.maximum(np.floor((nonzero.min(0) - 1) * scale).astype(int), 0)
        hi = np.minimum(np.ceil((nonzero.max(0) + 2) * scale).astype(int), self.native)
        rows = linear_operator((np.arange(lo[0], hi[0]) + 0.5) / scale[0] - 0.5, h)
        cols = linear_operator((np.arange(lo[1], hi[1]) + 0.5) / scale[1] - 0.5, w)
        native[:, lo[0]:hi[0], lo[1]:hi[1]] = _separable(np.ascontiguousarray(core), rows, cols)
        return stack_from_slice_images(native, self.slice_axis)


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


def _pad(small: NDArray[np.float32]) -> tuple[NDArray[np.float32], tuple[int, int]]:
    """Zero-pad ``[n, h, w]`` to multiples of :data:`PAD_MULTIPLE` and at least :data:`MIN_GRID_PX`,
    centred; returns it and its offset."""
    h, w = small.shape[1:]
    hp, wp = (max(-(-n // PAD_MULTIPLE) * PAD_MULTIPLE, MIN_GRID_PX) for n in (h, w))
    r, c = (hp - h) // 2, (wp - w) // 2
    padded = np.zeros((len(small), hp, wp), np.float32)
    padded[:, r:r + h, c:c + w] = small
    return padded, (r, c)


def with_neighbours(slices: NDArray[np.float32]) -> NDArray[np.float32]:
    """``[n, H, W]`` -> ``[n, 3, H, W]``: each slice between its neighbours (ends repeat themselves)."""
    ext = np.concatenate([slices[:1], slices, slices[-1:]])
    return np.stack([ext[:-2], ext[1:-1], ext[2:]], axis=1)


def localiser_inputs(volume: Volume, grid_mm: float) -> tuple[NDArray[np.float32], LocaliserGrid]:
    """The network inputs ``[n, 3, Hp, Wp]`` of a stack and the grid to map outputs back with."""
    axis = stack_axis(volume)
    images, pixel_mm = slice_images(volume.array, volume.affine, axis)
    images = np.asarray(images, np.float32)
    finite = np.isfinite(images)
    if not finite.all():                                                  # NaN and inf pixels count as 0
        images = np.where(finite, images, np.float32(0.0))
    scale = float(np.percentile(images[:, ::3, ::3], PERCENTILE))        # every 9th pixel: as good, 30x faster
    images = np.clip(images / scale, 0.0, 2.0) if scale > 0 else np.zeros_like(images)
    small = _resample(images, pixel_mm, grid_mm)
    padded, offset = _pad(small)
    x = with_neighbours(padded)
    grid = LocaliserGrid(tuple(volume.array.shape), axis, images.shape[1:], small.shape[1:], offset)
    return np.ascontiguousarray(x), grid


def target_maps(mask: NDArray, volume: Volume, grid_mm: float) -> NDArray[np.float32]:
    """A stack's brain mask on the network grid ``[n, Hp, Wp]`` (brain fraction per pixel): the
    training target that matches :func:`localiser_inputs` pixel for pixel."""
    images, pixel_mm = slice_images(np.asarray(mask, np.float32), volume.affine, stack_axis(volume))
    return _pad(np.clip(_resample(images, pixel_mm, grid_mm), 0.0, 1.0))[0]
