"""The scanner sweep's signal void: one dark ball, fixed in the scanner, in every stack of an acquisition."""

from __future__ import annotations

import numpy as np

from model_export.acquisitions import simulate_acquisition
from model_export.experiments.scanner_sweep import VOID_GAIN, VOID_RADIUS_MM, with_void
from tests.support.phantoms import phantom_brain


def test_the_void_is_one_ball_in_the_scanner_and_leaves_the_geometry_alone() -> None:
    img, mask, aff = phantom_brain(0)
    stacks = simulate_acquisition(img, mask, aff, np.random.default_rng(3), "mild", size=64, pixel_mm=1.6)
    dark = with_void(stacks, np.random.default_rng(4))
    centres = []
    for before, after in zip(stacks, dark):
        assert np.array_equal(after.volume.affine, before.volume.affine) and after.mask is before.mask
        np.testing.assert_array_equal(after.atlas_from_voxel, before.atlas_from_voxel)
        ratio = np.where(before.volume.array > 1e-3, after.volume.array / np.maximum(before.volume.array, 1e-3), 1.0)
        assert ratio.min() > VOID_GAIN - 0.01 and ratio.max() <= 1.0 + 1e-6
        deep = np.argwhere(ratio < VOID_GAIN + 0.02)                # the ball's core, well inside its radius
        assert len(deep) > 0
        world = deep @ before.volume.affine[:3, :3].T + before.volume.affine[:3, 3]
        centres.append(world.mean(axis=0))
        assert np.ptp(world, axis=0).max() < 2 * VOID_RADIUS_MM
    centres = np.array(centres)                                     # the same place in the scanner for every stack
    assert np.linalg.norm(centres - centres.mean(axis=0), axis=1).max() < 6.0
