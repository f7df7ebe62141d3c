"""N4's fit works on the voxel grid: a stack's geometry rounded by 1e-7 mm (float32 headers, as MRD
images and stream clients carry it) gives the same corrected voxels, to the bit."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from service.geometry import se3
from service.io.volume import Volume
from service.preprocess.bias import n4_correct


def test_n4_does_not_depend_on_the_rounding_of_the_stack_geometry() -> None:
    rng = np.random.default_rng(3)
    shape = (120, 110, 24)                                    # 1.125 mm pixels, 3.3 mm slices: shrink factors 7, 7, 2
    zz = np.linspace(-1, 1, shape[0])[:, None, None]
    image = (400 + 200 * np.exp(0.6 * zz) * np.ones(shape) + rng.normal(0, 20, shape)).astype(np.float32)
    mask = np.zeros(shape, bool)
    mask[30:90, 25:85, 3:21] = True
    for seed in range(6):                                      # oblique stacks: rounding tips the pick either way
        affine = np.eye(4)
        affine[:3, :3] = se3.so3_exp(np.random.default_rng(seed).normal(0, 0.6, 3)) * [1.125, 1.125, 3.3]
        affine[:3, 3] = [-71.3, 12.9, 40.1]
        stack = Volume(image, affine)
        rounded = replace(stack, affine=affine.astype(np.float32).astype(np.float64))
        assert np.array_equal(n4_correct(stack, mask), n4_correct(rounded, mask)), seed
