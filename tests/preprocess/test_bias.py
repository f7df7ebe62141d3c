"""N4's fit works on the voxel grid: a stack's geometry rounded by 1e-7 mm (float32 headers, as MRD
images and stream clients carry it) gives the same corrected voxels, to the bit; a stack stored with
its axes the other way gets the same correction."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from service.geometry import se3
from service.io.volume import Volume
from service.preprocess.bias import n4_correct


@pytest.mark.parametrize("spacing", [(1.125, 1.125, 3.3), (1.0, 1.0, 2.0)])
def test_n4_does_not_depend_on_the_rounding_of_the_stack_geometry(spacing: tuple[float, float, float]) -> None:
    """The same stack with its affine as a float64 and as a float32 header holds it: the same field.
    At 1 mm pixels the 20 mm margin of the fit region is a whole number of pixels, which float32's
    rounding (0.99999994 mm) made 21 (the region, the samples and the field then differed: the
    network's inputs by up to half their range)."""
    rng = np.random.default_rng(3)
    shape = (120, 110, 24)                                    # 1.125 mm pixels, 3.3 mm slices: shrink factors 7, 7, 2
    zz = np.linspace(-1, 1, shape[0])[:, None, None]
    image = (400 + 200 * np.exp(0.6 * zz) * np.ones(shape) + rng.normal(0, 20, shape)).astype(np.float32)
    mask = np.zeros(shape, bool)
    mask[30:90, 25:85, 3:21] = True
    for seed in range(6):                                      # oblique stacks: rounding tips the pick either way
        affine = np.eye(4)
        affine[:3, :3] = se3.so3_exp(np.random.default_rng(seed).normal(0, 0.6, 3)) * spacing
        affine[:3, 3] = [-71.3, 12.9, 40.1]
        stack = Volume(image, affine)
        rounded = replace(stack, affine=affine.astype(np.float32).astype(np.float64))
        assert np.array_equal(n4_correct(stack, mask), n4_correct(rounded, mask)), seed


def test_n4_corrects_a_stack_stored_the_other_way_alike() -> None:
    """The same stack with its slices stored last to first, or its rows or columns the other way (as
    another converter writes it), gets the same corrected voxels: the fit's blocks do not start at the
    first voxel. Sizes whose leftover voxels are odd and even in number."""
    rng = np.random.default_rng(5)
    for shape in ((121, 110, 23), (118, 103, 24)):
        x, y = np.linspace(-1, 1, shape[0])[:, None, None], np.linspace(-1, 1, shape[1])[None, :, None]
        image = (400 + 200 * np.exp(0.6 * x - 0.4 * y) * np.ones(shape) + rng.normal(0, 20, shape)).astype(np.float32)
        mask = np.zeros(shape, bool)
        mask[31:90, 22:85, 3:20] = True
        stack = Volume(image, np.diag([1.125, 1.125, 3.3, 1.0]))
        corrected = n4_correct(stack, mask)
        for flip in ((2,), (0,), (0, 1, 2)):
            other = n4_correct(Volume(np.flip(image, flip).copy(), stack.affine), np.flip(mask, flip))
            np.testing.assert_allclose(np.flip(other, flip), corrected, rtol=2e-5, err_msg=f"{shape} {flip}")


def test_n4_corrects_a_stack_stored_in_very_small_or_large_units_alike() -> None:
    """The same stack stored in units 1e-12 to 1e12 times as large gets the same correction, to
    float rounding: the fit mask's Otsu threshold is taken on one scale (ITK's histogram does not
    tell apart values that are small in absolute terms)."""
    rng = np.random.default_rng(7)
    shape = (96, 90, 16)
    x = np.linspace(-1, 1, shape[0])[:, None, None]
    image = (400 * np.exp(0.5 * x) * np.ones(shape) + rng.normal(0, 30, shape)).astype(np.float32)
    image[:, :20] = 0.0                                         # air: a fit image of two classes
    mask = np.zeros(shape, bool)
    mask[20:80, 25:80, 2:14] = True
    stack = Volume(image, np.diag([1.2, 1.2, 3.0, 1.0]))
    corrected = n4_correct(stack, mask)
    for unit in (1e-12, 1e-9, 1e-6, 1e6, 1e12):
        scaled = n4_correct(Volume(image * np.float32(unit), stack.affine), mask) / np.float32(unit)
        np.testing.assert_allclose(scaled, corrected, rtol=1e-4, atol=1e-3, err_msg=str(unit))


def test_a_mask_a_voxel_larger_at_its_edge_leaves_the_field_where_it_was() -> None:
    """The fit region (the mask's box and 20 mm) one voxel larger: the fit's samples lie on a lattice
    through the stack's middle, so none moves and the field is the same wherever both regions reach
    (before, every sample moved by half a voxel: the network's inputs changed on 23 of 24 slices of
    a real stack, its poses by up to 13 mm)."""
    rng = np.random.default_rng(3)
    shape = (120, 110, 24)
    zz = np.linspace(-1, 1, shape[0])[:, None, None]
    image = (400 + 200 * np.exp(0.6 * zz) * np.ones(shape) + rng.normal(0, 20, shape)).astype(np.float32)
    mask = np.zeros(shape, bool)
    mask[30:90, 25:85, 3:21] = True
    stack = Volume(image, np.diag([1.125, 1.125, 3.3, 1.0]))
    grown = mask.copy()
    grown[29, 50, 10] = True                                    # the box now starts a voxel sooner along x
    before, after = n4_correct(stack, mask), n4_correct(stack, grown)
    assert not np.array_equal(before[11], after[11])            # the voxel row the larger region added
    np.testing.assert_allclose(after[12:], before[12:], rtol=1e-6)
