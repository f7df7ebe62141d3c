"""THE slice preprocessing: what the network sees, shared by the service and by training.

For a batch of 2D slices with their masks and in-plane pixel size, in order:

1. mask and rescale to 0-255 with 1 %/99 % pruning (:func:`~service.preprocess.intensity.rescale_0_255`);
2. find the mask centroid in the slice frame (mm);
3. resample to the model's ``L x L`` grid of ``s`` mm pixels centred on that centroid (bilinear;
   Gaussian anti-aliasing first when the model's pixels are coarser than the input's).

Slice frame of an input image ``[H, W]`` with pixel size ``(row_mm, col_mm)``: pixel ``(r, c)`` at
``x = (c - (W-1)/2) col_mm``, ``y = (r - (H-1)/2) row_mm`` -- the package convention of
:mod:`service.geometry` generalised to rectangular grids. The network frame is that same frame
translated by the centroid: ``p_input = p_network + (cx, cy, 0)``. So a pose ``P`` predicted for the
network input places the input slice at ``P @ translate(-cx, -cy, 0)``, and a training label is
``recentre(P_acquired, centroid)``.

Example:
    >>> import numpy as np
    >>> img = np.zeros((1, 40, 40)); img[0, 5:15, 20:30] = np.arange(1.0, 101.0).reshape(10, 10)
    >>> out = preprocess_slices(img, img > 0, (1.0, 1.0), size=16, pixel_out_mm=1.0)
    >>> out.centroid_mm.round(2).tolist()          # (x, y) of the box centre
    [[5.0, -10.0]]
    >>> float(out.inputs[0, 8, 8]) > 0
    True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from service.geometry.pose import pixel_offsets_mm, translate
from service.geometry.sampling import FWHM_TO_SIGMA
from service.preprocess.intensity import rescale_0_255
from service.preprocess.stack import mask_box


@dataclass
class PreparedSlices:
    """Network inputs and how they relate to the input slices.

    Attributes:
        inputs: ``[B, L, L]`` float32, 0-255, what the network is fed.
        centroid_mm: ``[B, 2]`` mask centroid (x, y) in the input slice frame, mm.
        mask_pixels: ``[B]`` mask area in the input slice, pixels.
        mask_fraction: ``[B]`` share of the network input covered by the resampled mask; 0 where the
            slice's pixels inside its mask are all alike but for under 1 % of them (the rescale's
            percentiles meet: a blank or saturated slice shows nothing).
    """

    inputs: NDArray[np.float32]
    centroid_mm: NDArray[np.float64]
    mask_pixels: NDArray[np.float64]
    mask_fraction: NDArray[np.float64]

    def input_from_network(self) -> NDArray[np.float64]:
        """``[B, 4, 4]``: network-frame mm -> input-slice-frame mm (a pure in-plane translation)."""
        c = self.centroid_mm
        return translate(np.concatenate([c, np.zeros((len(c), 1))], axis=1))


def _frame_coordinates(shape: tuple[int, int], pixel_mm: tuple[float, float]) -> tuple[NDArray, NDArray]:
    h, w = shape
    x = (np.arange(w) - (w - 1) / 2.0) * pixel_mm[1]
    y = (np.arange(h) - (h - 1) / 2.0) * pixel_mm[0]
    return x, y


def preprocess_slices(
    images: ArrayLike,
    masks: ArrayLike,
    pixel_mm: tuple[float, float],
    size: int,
    pixel_out_mm: float,
) -> PreparedSlices:
    """Mask, rescale, centre and resample slices ``[B, H, W]`` to network inputs ``[B, L, L]``.

    Args:
        images: raw (bias-corrected) slice intensities.
        masks: region-of-interest masks on the same grid (bool or 0/1).
        pixel_mm: input pixel size ``(row_mm, col_mm)``.
        size: ``L``.
        pixel_out_mm: the model's pixel size ``s`` (mm).
    """
    s = float(pixel_out_mm)
    m_full = np.asarray(masks) > 0.5
    b, h, w = m_full.shape
    sig = [np.sqrt(max(s**2 - p**2, 0.0)) * FWHM_TO_SIGMA / p for p in pixel_mm]
    blur = max(sig) > 0.2                                  # anti-alias when the output grid is coarser
    # Everything outside the masks is 0 after the rescale: work on their bounding box, with room
    # for the anti-aliasing kernel (4 sigma) and the bilinear sampler. The result is the same.
    box = mask_box(m_full.any(axis=0), [int(np.ceil(4.0 * g)) + 2 if blur else 2 for g in sig]) or (slice(0, 1),) * 2
    (r0, r1), (c0, c1) = ((b.start, b.stop) for b in box)
    img = np.asarray(np.asarray(images)[:, r0:r1, c0:c1], dtype=np.float32)
    m = m_full[:, r0:r1, c0:c1]
    scaled = rescale_0_255(img, m)
    x, y = _frame_coordinates((h, w), pixel_mm)
    x, y = x[c0:c1], y[r0:r1]
    counts = m.sum(axis=(1, 2)).astype(np.float64)
    safe = np.maximum(counts, 1.0)
    cx = np.where(counts > 0, m.sum(axis=1) @ x / safe, 0.0)
    cy = np.where(counts > 0, m.sum(axis=2) @ y / safe, 0.0)
    if blur:
        scaled = ndimage.gaussian_filter(scaled, (0.0, sig[0], sig[1]), mode="constant")

    grid = pixel_offsets_mm(size, s)
    cols = (cx[:, None] + grid[None, :]) / pixel_mm[1] + (w - 1) / 2.0 - c0     # [B, L], in the box
    rows = (cy[:, None] + grid[None, :]) / pixel_mm[0] + (h - 1) / 2.0 - r0     # [B, L]
    both = sample_grid(np.concatenate([scaled, m.astype(np.float32)]), np.concatenate([rows, rows]),
                       np.concatenate([cols, cols]))
    flat = ~(scaled.reshape(b, -1) > 0).any(axis=1)        # no contrast in the region: nothing to see
    return PreparedSlices(
        inputs=both[:b].astype(np.float32),
        centroid_mm=np.stack([cx, cy], axis=1),
        mask_pixels=counts,
        mask_fraction=np.where(flat, 0.0, (both[b:].reshape(b, -1) > 0.5).mean(axis=1)),
    )


def sample_grid(images: NDArray[np.float32], rows: NDArray, cols: NDArray) -> NDArray[np.float32]:
    """Bilinear samples ``[B, L, M]`` of ``images [B, H, W]`` at the axis-aligned grids ``rows [B, L]``
    x ``cols [B, M]`` (pixel coordinates); 0 where a row or column lies outside the image.

    The grid of each image is a product of rows and columns, so the interpolation is separable: the
    rows are blended first (``B x L x W`` values), then the columns, instead of eight-point trilinear
    sampling of every output pixel. The values equal ``scipy.ndimage.map_coordinates(order=1,
    mode="constant")`` at the same points.

    Example:
        >>> img = np.arange(12, dtype=np.float32).reshape(1, 3, 4)
        >>> sample_grid(img, np.array([[0.5, 2.0, 2.5]]), np.array([[1.0, 1.5]])).tolist()
        [[[3.0, 3.5], [9.0, 9.5], [0.0, 0.0]]]
    """
    b, h, w = images.shape

    def weights(c: NDArray, n: int) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        low = np.clip(np.floor(c), 0, max(n - 2, 0)).astype(np.intp)
        return low, np.minimum(low + 1, n - 1), (c - low).astype(np.float32), ((c >= 0) & (c <= n - 1))

    r0, r1, fr, r_in = weights(np.asarray(rows, np.float64), h)
    c0, c1, fc, c_in = weights(np.asarray(cols, np.float64), w)
    index = np.arange(b)[:, None]
    blended = images[index, r0] * ((1 - fr) * r_in)[..., None] + images[index, r1] * (fr * r_in)[..., None]
    return (np.take_along_axis(blended, np.broadcast_to(c0[:, None, :], (b, r0.shape[1], c0.shape[1])), 2)
            * ((1 - fc) * c_in)[:, None, :]
            + np.take_along_axis(blended, np.broadcast_to(c1[:, None, :], (b, r0.shape[1], c1.shape[1])), 2)
            * (fc * c_in)[:, None, :])
