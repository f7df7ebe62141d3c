"""How noisy a stack's slices are as the pose network sees them.

A low-field scanner's stacks (0.55 T) are noisier than the slices the pose network was trained and
calibrated on, and their poses are posed less well than their expected errors say: on simulated
acquisitions with Rician noise of 15 % of the bright end, 0.3 mm further from the truth at mild
motion, 0.8 mm under jumps, and RMS E.D. over RMS expected error 1.15-1.24 (docs/accuracy.md,
"Other scanners' acquisitions"). :func:`input_noise` measures the noise where it acts, in the
network's inputs (0-255, 1.25 mm pixels, the brain alone), so a stack that is noisier than the
network knows is told apart from one it knows, whatever the scanner's pixel size or intensity
range.

The estimate is Immerkær's (1996): the image convolved with the 3 x 3 kernel
``[[1, -2, 1], [-2, 4, -2], [1, -2, 1]]``, which cancels smooth intensity up to a plane's and
passes white noise with a gain of 6; the median absolute response (over the brain's inner
pixels, as a robust SD: x 1.4826) divided by 6 is the noise's SD. The brain's texture adds a little:
noise-free simulated slices give 0.003-0.007 of the input's range. The network's resampling smooths noise,
so an input's figure is below the noise of the stack it came from (simulated acquisitions with
Rician noise of 3 / 8 / 15 % of the bright end: 0.025 / 0.056 / 0.083; the real scans at hand
0.015-0.021).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

KERNEL = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]], np.float32)
"""Immerkær's kernel: the difference of two discrete Laplacians; white noise of SD s gives s x 6."""
KERNEL_GAIN = 6.0
"""``sqrt(sum(KERNEL ** 2))``: the SD of the response to unit white noise."""
MIN_PIXELS = 50
"""Inner brain pixels an input slice needs to count (an end slice's cap tells little)."""
NOISY_INPUT = 0.06
"""Input noise (a share of the input's 0-255 range) above which a stack is noisier than the
pipeline's noise benchmarks show it holds: simulated acquisitions at 8 % noise give about 0.056 and
are posed as well as at 3 %; at 15 % (about 0.083) poses and expected errors lose, as the module
says."""


def input_noise(inputs: NDArray[np.float32]) -> float:
    """The noise SD of network inputs ``[B, L, L]`` (0-255, zero outside the brain) as a share of
    their range, pooled over every slice with :data:`MIN_PIXELS` inner brain pixels (NaN: none has).

    Example (a smooth ramp with white noise of SD 10 on the 0-255 scale: about 10 / 255):
        >>> rng = np.random.default_rng(0)
        >>> ramp = np.tile(np.linspace(40.0, 200.0, 64), (64, 1))
        >>> x = np.zeros((3, 80, 80), np.float32); x[:, 8:72, 8:72] = ramp + rng.normal(0, 10, (3, 64, 64))
        >>> round(input_noise(x), 3), round(10 / 255, 3)
        (0.039, 0.039)
        >>> bool(np.isnan(input_noise(np.zeros((2, 16, 16), np.float32))))
        True
    """
    responses = []
    for image in np.asarray(inputs, np.float32):
        inner = ndimage.binary_erosion(image > 0, np.ones((3, 3), bool), iterations=2)   # off the mask's edge
        if int(inner.sum()) >= MIN_PIXELS:
            responses.append(ndimage.convolve(image, KERNEL, mode="nearest")[inner])
    if not responses:
        return float("nan")
    mad = float(np.median(np.abs(np.concatenate(responses))))
    return 1.4826 * mad / KERNEL_GAIN / 255.0
