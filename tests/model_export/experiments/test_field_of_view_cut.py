"""The field-of-view experiment's cut: the stack and its mask end inside the brain, their voxels and
geometry otherwise as sent (the answers compare slice by slice)."""

from __future__ import annotations

import numpy as np

from model_export.experiments.field_of_view_cut import cut
from service.io.volume import Volume


def test_the_cut_ends_the_stack_and_its_mask_a_share_into_the_brain_and_keeps_their_voxels() -> None:
    affine = np.diag([1.1, 1.1, 3.0, 1.0])
    affine[:3, 3] = [-20.0, 5.0, 7.0]
    image = np.random.default_rng(0).random((40, 30, 6)).astype(np.float32)
    mask = np.zeros((40, 30, 6), np.uint8)
    mask[10:30, 5:25, 1:5] = 1                              # the brain: rows 10-29
    volume, kept = cut(Volume(image, affine), Volume(mask, affine), 0.75)
    assert volume.array.shape == kept.array.shape == (25, 30, 6)          # 10 + 0.75 x 20 rows
    np.testing.assert_array_equal(volume.array, image[:25])
    np.testing.assert_array_equal(kept.array, mask[:25])
    np.testing.assert_allclose(volume.affine, affine)                      # voxel (i, j, k) where it was
    assert kept.array[24].any() and kept.array[10:25].sum() == 15 * 20 * 4  # the brain runs to the edge
