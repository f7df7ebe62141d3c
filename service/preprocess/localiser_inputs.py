"""THE localiser's input: what the brain-localisation network sees, shared by the service and training.

For a stack (any orientation, any in-plane pixel size, whole uterus or cropped), in order:

1. split it into slices along its slice axis (:func:`~service.preprocess.stack.slice_images`);
2. scale intensities by the stack's 99.5th percentile (of every third pixel along rows and columns;
   clipped to 0..2), so that no scanner's units matter;
3. resample every slice to square pixels of ``grid_mm`` (the model's; Gaussian anti-aliasing first,
   so a 0.5 mm and a 1.5 mm acquisition look alike), its field of view kept;
4. pad with zeros to a multiple of :data:`PAD_MULTIPLE` on each side, centred;
5. stack each slice with its two neighbours along the slice axis as three channels (2.5D; the end
   slices repeat themselves).

:meth:`LocaliserGrid.to_stack` maps the network's per-pixel output back onto the stack's own grid.

Example:
    >>> import numpy as np
    >>> from service.io.volume import Volume
    >>> vol = Volume(np.random.default_rng(0).random((100, 80, 6), np.float32), np.diag([1.25, 1.25, 3.0, 1.0]))
    >>> x, grid = localiser_inputs(vol, grid_mm=2.5)
    >>> x.shape                                       # 6 slices, 3 channels, 80 x 50 px padded to 16s
    (6, 3, 48, 64)
    >>> grid.to_stack(x[:, 1]).shape == vol.array.shape
    True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from service.geometry.sampling import FWHM_TO_SIGMA
from service.io.volume import Volume
from service.preprocess.stack import slice_axis_of, slice_images, stack_from_slice_images

PAD_MULTIPLE = 16
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
        pixel areas aligned as :func:`scipy.ndimage.zoom` with ``grid_mode`` aligns them). Only the
        native pixels near the maps' non-zero box are interpolated; the rest are 0."""
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
        rows = (np.arange(lo[0], hi[0]) + 0.5) / scale[0] - 0.5
        cols = (np.arange(lo[1], hi[1]) + 0.5) / scale[1] - 0.5
        k, rr, cc = np.meshgrid(np.arange(len(core)), rows, cols, indexing="ij")
        native[:, lo[0]:hi[0], lo[1]:hi[1]] = ndimage.map_coordinates(core, [k, rr, cc], order=1, mode="nearest")
        return stack_from_slice_images(native, self.slice_axis)


def _resample(images: NDArray[np.float32], pixel_mm: tuple[float, float], grid_mm: float) -> NDArray[np.float32]:
    """Slices ``[n, H, W]`` to square ``grid_mm`` pixels over the same field of view (bilinear, Gaussian
    anti-aliasing first where the grid is coarser)."""
    factors = np.array(pixel_mm) / grid_mm                       # < 1: shrinking
    sigma = [0.0] + [FWHM_TO_SIGMA * np.sqrt(max(1.0 / f ** 2 - 1.0, 0.0)) for f in factors]
    if max(sigma) > 0:
        images = ndimage.gaussian_filter(images, sigma, mode="nearest", truncate=3.0)
    size = np.maximum(1, np.round(np.array(images.shape[1:]) * factors)).astype(int)
    zoom = (1.0, *(size / np.array(images.shape[1:])))
    return ndimage.zoom(images, zoom, order=1, mode="nearest", grid_mode=True)


def _pad(small: NDArray[np.float32]) -> tuple[NDArray[np.float32], tuple[int, int]]:
    """Zero-pad ``[n, h, w]`` to multiples of :data:`PAD_MULTIPLE`, centred; returns it and its offset."""
    h, w = small.shape[1:]
    hp, wp = -(-h // PAD_MULTIPLE) * PAD_MULTIPLE, -(-w // PAD_MULTIPLE) * PAD_MULTIPLE
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
    axis = slice_axis_of(volume.spacing)
    images, pixel_mm = slice_images(volume.array, volume.affine, axis)
    images = np.nan_to_num(np.asarray(images, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
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
    images, pixel_mm = slice_images(np.asarray(mask, np.float32), volume.affine, slice_axis_of(volume.spacing))
    return _pad(np.clip(_resample(images, pixel_mm, grid_mm), 0.0, 1.0))[0]
