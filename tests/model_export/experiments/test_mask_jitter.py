"""The mask-jitter experiment's changed masks: one pixel in the plane of the slices, nowhere else."""

from __future__ import annotations

import numpy as np
import pytest

from model_export.experiments.mask_jitter import changed


def _cylinder(axis: int) -> np.ndarray:
    """A disc of radius 10 px on slices 2-5 of 8 along ``axis`` (40 x 40 px in plane)."""
    yy, xx = np.mgrid[:40, :40]
    disc = (yy - 20) ** 2 + (xx - 20) ** 2 <= 100
    stack = np.zeros((40, 40, 8), bool)
    stack[:, :, 2:6] = disc[:, :, None]
    return np.moveaxis(stack, 2, axis)


@pytest.mark.parametrize("axis", [0, 2])
def test_each_change_moves_the_outline_by_one_pixel_within_each_slice(axis: int) -> None:
    mask = _cylinder(axis)
    rng = np.random.default_rng(0)
    eroded, dilated, jittered = (changed(mask, axis, how, rng) for how in ("erode", "dilate", "jitter"))
    slices_with = lambda m: np.flatnonzero(np.moveaxis(m, axis, 2).any(axis=(0, 1))).tolist()  # noqa: E731
    for m in (eroded, dilated, jittered):                     # no slice gains or loses the brain
        assert slices_with(m) == [2, 3, 4, 5]
    assert not (eroded & ~mask).any() and not (mask & ~dilated).any()
    assert eroded.sum() < mask.sum() < dilated.sum()
    assert not (jittered & ~dilated).any() and not (eroded & ~jittered).any()      # only the outline's band moves
    assert (jittered != mask).any()
