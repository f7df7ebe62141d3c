"""Intensity normalisation: the paper's 0-255 rescale with the top and bottom 1 % pruned.

The percentiles are taken over the region of interest of each slice (vectorised over a batch).
This is the paper's rescale applied per slice instead of per volume, so that a training slice and
an uploaded slice are normalised by exactly the same rule, and slice-to-slice intensity changes of
real stacks (spin history, motion) do not leak into the network input.

Example:
    >>> import numpy as np
    >>> img = np.arange(100, dtype=float).reshape(1, 10, 10)
    >>> out = rescale_0_255(img, np.ones_like(img, bool))
    >>> float(out.min()), float(out.max())
    (0.0, 255.0)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core.errors import UnusableImage

LOW_PERCENTILE = 1.0
HIGH_PERCENTILE = 99.0
FLAT_SPAN = 1e-6
"""A slice whose pruned range spans less than this share of its largest magnitude is flat (one value
up to float rounding) and rescales to 0: a share, not a number of units, so that a stack stored in
small units (brain values of 1e-9, say) is rescaled as the same stack in large ones."""


def masked_percentiles(images: ArrayLike, masks: ArrayLike, q: tuple[float, float]) -> NDArray[np.float64]:
    """Per-slice percentiles ``[B, len(q)]`` of ``images [B, H, W]`` inside ``masks`` (NaN if empty)."""
    x = np.asarray(images)
    m = np.asarray(masks, dtype=bool)
    out = np.full((x.shape[0], len(q)), np.nan)
    for i in np.flatnonzero(m.reshape(len(m), -1).any(axis=1)):   # a slice's brain only: no NaN-padded rows
        out[i] = np.percentile(x[i][m[i]].astype(np.float64), q)
    return out


def rescale_0_255(
    images: ArrayLike,
    masks: ArrayLike,
    low: float = LOW_PERCENTILE,
    high: float = HIGH_PERCENTILE,
) -> NDArray[np.float32]:
    """Mask, clip to the ``[low, high]`` percentiles inside the mask and rescale to 0-255.

    Pixels outside the mask are 0; slices with an empty mask, and flat slices (:data:`FLAT_SPAN`),
    are all 0. The result does not depend on the units the image is stored in.

    Example (one slice in ordinary units and in very small ones):
        >>> img = np.arange(16.0).reshape(1, 4, 4)
        >>> bool(np.allclose(rescale_0_255(img * 1e-12, img >= 0), rescale_0_255(img, img >= 0)))
        True
    """
    x = np.asarray(images, dtype=np.float32)
    m = np.asarray(masks, dtype=bool)
    p = masked_percentiles(x, m, (low, high)).astype(np.float32)
    lo, hi = p[:, 0, None, None], p[:, 1, None, None]
    span = hi - lo
    varies = span > FLAT_SPAN * np.maximum(np.abs(lo), np.abs(hi))        # False for NaN (an empty mask) too
    out = (np.clip(x, lo, hi) - lo) / np.where(varies, span, 1.0) * 255.0
    return np.where(m & varies & np.isfinite(out), out, 0.0).astype(np.float32)


SIGNAL_LOST = "signal_lost"
"""The name of such a slice's fault wherever a reason is given: a stream's slices to acquire again, a
job's slices left out of its volume."""
SIGNAL_LOSS_LEVEL = 0.4
"""A brain pixel under this fraction of its stack's brain median is dark."""
SIGNAL_LOSS_SHARE = 0.15
"""A slice with more of its brain's pixels dark than this has lost its signal (a signal void,
intra-slice motion): above what clean real slices hold, noisy ones included, and under what real
voids leave (docs/reports/consistency-experiments.md, "Signal loss over runs of slices")."""


def signal_lost(images: ArrayLike, masks: ArrayLike) -> NDArray[np.bool_]:
    """Per slice of a stack, whether its brain has lost its signal: over :data:`SIGNAL_LOSS_SHARE` of
    the pixels in its mask under :data:`SIGNAL_LOSS_LEVEL` times the median of the stack's brain
    pixels (every slice's together, so a stack of dark tissue is its own reference). Such a slice's
    image has nothing to compare with the other stacks' where they cross; its network pose, read off
    the mask's outline as much as the brain, still counts. Slices without mask: False.

    Example (three slices of brain at 100, the middle one dark over half of it):
        >>> import numpy as np
        >>> x = np.full((3, 4, 4), 100.0); x[1, :2] = 10.0
        >>> signal_lost(x, np.ones_like(x, bool)).tolist()
        [False, True, False]
    """
    x = np.asarray(images, dtype=np.float32)
    m = np.asarray(masks, dtype=bool)
    if not m.any():
        return np.zeros(len(x), bool)
    dark = (x < SIGNAL_LOSS_LEVEL * float(np.median(x[m]))) & m
    counts = m.reshape(len(m), -1).sum(axis=1)
    return (counts > 0) & (dark.reshape(len(m), -1).sum(axis=1) > SIGNAL_LOSS_SHARE * counts)


SAMPLED_VOXELS = 1 << 16
"""How many of a stack's voxels (evenly strided) :func:`two_values` looks at before it looks at all."""


def two_values(array: NDArray) -> tuple[float, float] | None:
    """The two values of an array that holds exactly two (a mask, 0 and 1 or 0 and 255), else None.

    No MR image holds two values: a stack that does is a mask sent where a stack belongs (a folder's
    ``*.nii.gz`` taking its masks along). A strided sample decides first, so an image costs a
    look at :data:`SAMPLED_VOXELS` voxels; one value (a blank stack) is an image with no brain in it.

    Example:
        >>> two_values(np.array([[0, 1], [1, 1]], np.uint8)), two_values(np.zeros((2, 2))), two_values(np.arange(4.0))
        ((0.0, 1.0), None, None)
    """
    flat = array.reshape(-1)
    if flat.size == 0 or len(np.unique(flat[::max(1, flat.size // SAMPLED_VOXELS)])) > 2:
        return None
    lo, hi = float(flat.min()), float(flat.max())
    if lo == hi or np.count_nonzero((flat != lo) & (flat != hi)):
        return None
    return lo, hi


def check_stack_values(stacks: list[tuple[str, NDArray]]) -> None:
    """422 naming the first stack (``(name, voxels)``) that holds two values alone (:func:`two_values`).

    Example:
        >>> check_stack_values([("a.nii.gz", np.arange(8.0)), ("a_mask.nii.gz", np.eye(3))])
        Traceback (most recent call last):
        ...
        service.core.errors.UnusableImage: stacks: a_mask.nii.gz holds the values 0 and 1 alone: a mask, not an MR image; send it as its stack's mask (the form field masks; svrnet --mask), or leave it out
    """
    for name, voxels in stacks:
        if (values := two_values(voxels)) is not None:
            raise UnusableImage(f"stacks: {name} holds the values {values[0]:g} and {values[1]:g} alone: a mask, "
                                "not an MR image; send it as its stack's mask (the form field masks; svrnet --mask), "
                                "or leave it out")
