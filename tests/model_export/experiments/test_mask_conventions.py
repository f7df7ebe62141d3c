"""The manual outline's offset from a mask, measured in the slices' planes."""

from __future__ import annotations

import numpy as np

from model_export.experiments.mask_conventions import outline_offsets_mm


def test_an_outline_drawn_two_pixels_out_lies_two_pixel_sizes_outside() -> None:
    found = np.zeros((30, 30, 5), bool)
    found[10:20, 10:20, 1:4] = True
    manual = np.zeros_like(found)
    manual[8:22, 8:22, 1:4] = True                          # 2 pixels further out on every side
    in_plane = np.array([1.5, 1.5, 1e6])
    offsets = outline_offsets_mm(manual, found, in_plane)
    assert np.median(offsets) == 3.0 and offsets.min() > 0
    inside = outline_offsets_mm(found, manual, in_plane)    # the other way round: inside, negative
    assert np.median(inside) < 0
