"""How noisy a stack's slices are for the pose network.

A low-field scanner's stacks (0.55 T) are noisier than the slices the pose network was trained and
calibrated on, and are posed less well than the network's spread says, most on coarse pixels
(docs/accuracy.md, "Other scanners' acquisitions"). :func:`input_noise` puts a number on a stack's
noise in the units the network sees it in, so that a stack noisier than the network knows is told
apart, and :func:`noise_error_mm` what that noise costs beyond the network's spread (mostly a
larger turn and shift of the whole request, which the slices' agreement cannot show), as the
model's calibration says: the pipeline adds it to the stack's expected errors.

The noise is measured on the slices as the scanner wrote them, on the 0-255 scale the network's
inputs are rescaled to (the 1st to 99th percentile inside the mask), with Immerkær's estimate
(1996): the image convolved with the 3 x 3 kernel ``[[1, -2, 1], [-2, 4, -2], [1, -2, 1]]``, which
cancels smooth intensity up to a plane's and passes white noise with a gain of 6; the median absolute
response over the brain's inner pixels (as a robust SD: x 1.4826) divided by 6 is the noise's SD.
It is then carried to the network's pixel size: resampling pixels finer than the network's
(1.25 mm) averages ``(1.25 / p)^2`` of them, which divides the noise by ``1.25 / p``; pixels
coarser than it are interpolated and keep their noise. Measured on the resampled inputs
themselves, the estimate would miss that noise, which interpolation makes smooth (a stack of coarse
pixels would read much less noisy than one of fine pixels at the same noise).

Pixels much finer than the network's are also read about the network's pixel apart
(:func:`decimated`): scanners write interpolated reconstructions (a 512 x 512 or 640 x 640 matrix
of 0.5-0.7 mm pixels from an acquisition of about 1.1 mm), whose noise is smooth over two or more
pixels, and the kernel, which sees only the finest scale, reads such a stack many times less
noisy than the same acquisition written at its own pixels. Where the pixels so far apart read
much noisier than all of them (:data:`SMOOTH_NOISE`: white noise reads alike), the noise is smooth
over the pixels and the estimate is theirs (the readings of one real stack at its own and at
interpolated pixels: docs/accuracy.md).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from service.core.hinge import hinge_mm
from service.preprocess.intensity import rescale_0_255
from service.preprocess.stack import mask_box

KERNEL = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]], np.float32)
"""Immerkær's kernel: the difference of two discrete Laplacians; white noise of SD s gives s x 6."""
KERNEL_GAIN = 6.0
"""``sqrt(sum(KERNEL ** 2))``: the SD of the response to unit white noise."""
MIN_PIXELS = 50
"""Inner brain pixels a slice needs to count (an end slice's cap tells little)."""
NOISY_INPUT = 0.10
"""Input noise (a share of the inputs' 0-255 range) above which a stack is noisier than the network
learnt and the pipeline's benchmarks hold (``beyond_calibration``): above what the simulated
acquisitions of moderate noise read and well above the real scans at hand (their readings:
docs/accuracy.md)."""


SMOOTH_NOISE = 2.0
"""White noise reads the same on every second or third pixel as on all of them (a little more, where
pixels farther apart show the brain's texture); noise that reads this many times more there is
smooth over the pixels (an interpolated reconstruction), and the estimate is taken there."""


def inner_responses(images: NDArray[np.float32], masks: NDArray[np.bool_]) -> NDArray[np.float32]:
    """The kernel's responses (each slice of ``images [n, H, W]`` in its own plane) at the pixels two
    pixels inside ``masks``, off the mask's edge where the brain ends and the kernel would see it, in
    the slices that hold :data:`MIN_PIXELS` such pixels."""
    inner = ndimage.binary_erosion(masks, np.ones((1, 3, 3), bool), iterations=2)
    inner &= (inner.sum(axis=(1, 2)) >= MIN_PIXELS)[:, None, None]
    return ndimage.convolve(np.asarray(images, np.float32), KERNEL[None], mode="nearest")[inner]


def input_noise(images: ArrayLike, masks: ArrayLike, pixel_mm: tuple[float, float], grid_mm: float) -> float:
    """The noise SD a stack's slices ``images [n, H, W]`` (``masks`` the brain's, pixels of
    ``pixel_mm``) carry into the pose network's inputs of ``grid_mm`` pixels, as a share of the inputs'
    0-255 range (NaN: no slice holds enough brain to tell).

    Example (a smooth ramp from 40 to 200 with white noise of SD 10: 10 over the ramp's stretch to
    0-255, on 1.25 mm pixels; on pixels of half that size, four of which make one input pixel, half of it):
        >>> rng = np.random.default_rng(0)
        >>> ramp = np.tile(np.linspace(40.0, 200.0, 64), (64, 1))
        >>> x = np.zeros((3, 80, 80), np.float32); x[:, 8:72, 8:72] = ramp + rng.normal(0, 10, (3, 64, 64))
        >>> m = x > 0
        >>> scale = 255.0 / np.subtract(*np.percentile(x[m], [99, 1]))      # the rescale's stretch
        >>> round(float(input_noise(x, m, (1.25, 1.25), 1.25) / scale), 3), round(10 / 255, 3)
        (0.038, 0.039)
        >>> round(float(input_noise(x, m, (0.625, 0.625), 1.25) / scale), 3)
        0.019
        >>> bool(np.isnan(input_noise(np.zeros((2, 16, 16)), np.zeros((2, 16, 16), bool), (1.0, 1.0), 1.25)))
        True
    """
    masks = np.asarray(masks, bool)
    box = mask_box(masks.any(axis=0), [1, 1])               # the brain's rows and columns: all that counts
    if box is None:
        return float("nan")
    images, masks = np.asarray(images, np.float32)[:, box[0], box[1]], masks[:, box[0], box[1]]
    sd = pixel_noise(images, masks)
    apart, apart_masks, apart_mm = decimated(images, masks, pixel_mm, grid_mm)
    if apart_mm != tuple(pixel_mm):
        sd_apart = pixel_noise(apart, apart_masks)
        if sd_apart > SMOOTH_NOISE * sd:             # smooth over the pixels: the acquired pixels' noise
            sd, pixel_mm = sd_apart, apart_mm
    averaged = np.sqrt(min(1.0, pixel_mm[0] / grid_mm) * min(1.0, pixel_mm[1] / grid_mm))
    return float(sd * averaged)


def pixel_noise(images: NDArray[np.float32], masks: NDArray[np.bool_]) -> float:
    """The noise SD of ``images`` at their own pixels on the 0-255 scale, as a share of it (NaN: too
    little brain to tell)."""
    responses = inner_responses(rescale_0_255(images, masks), masks)
    if not responses.size:
        return float("nan")
    return 1.4826 * float(np.median(np.abs(responses))) / KERNEL_GAIN / 255.0


def decimated(images: NDArray[np.float32], masks: NDArray[np.bool_], pixel_mm: tuple[float, float],
              grid_mm: float) -> tuple[NDArray[np.float32], NDArray[np.bool_], tuple[float, float]]:
    """Every ``round(grid_mm / p)``-th pixel of ``images [n, H, W]`` and ``masks`` along each in-plane
    axis (``p`` its pixel size; axes of pixels near or above ``grid_mm`` whole), and their spacing:
    pixels about an acquired pixel apart, where a reconstruction was interpolated to finer ones.

    Example (0.6 mm pixels: every second, 1.2 mm apart; 1.0 mm pixels all):
        >>> x, m, p = decimated(np.ones((1, 8, 8), np.float32), np.ones((1, 8, 8), bool), (0.6, 1.0), 1.25)
        >>> x.shape, p
        ((1, 4, 8), (1.2, 1.0))
    """
    f = [max(1, int(round(grid_mm / q))) for q in pixel_mm]
    return images[:, ::f[0], ::f[1]], masks[:, ::f[0], ::f[1]], (pixel_mm[0] * f[0], pixel_mm[1] * f[1])


def noise_error_mm(level: ArrayLike, calibration: tuple[float, float] | None) -> NDArray[np.float64]:
    """The error (mm) slices of input noise ``level`` carry beyond what the network's spread says, as
    the model's ``noise_error`` calibration ``(onset, slope)`` gives it: ``slope x max(0, level -
    onset)``; 0 without a calibration or where the noise is unknown (NaN).

    Example:
        >>> noise_error_mm([0.05, 0.15, float("nan")], (0.1, 40.0)).round(2).tolist()
        [0.0, 2.0, 0.0]
        >>> noise_error_mm(0.2, None).tolist()
        0.0
    """
    return hinge_mm(level, calibration)


def stack_noise(levels: ArrayLike) -> float:
    """One stack's input noise from its slices' (or parts') estimates: their median where known (NaN
    where none is).

    Example:
        >>> stack_noise([0.12, float("nan"), 0.10, 0.11]), bool(np.isnan(stack_noise([float("nan")])))
        (0.11, True)
    """
    levels = np.asarray(levels, np.float64)
    known = levels[np.isfinite(levels)]
    return float(np.median(known)) if known.size else float("nan")
