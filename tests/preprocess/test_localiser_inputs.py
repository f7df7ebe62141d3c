"""The localiser's input function: grids, padding, the way back to the stack, and the same picture
whatever the scanner's pixel size."""

from __future__ import annotations

import numpy as np
import pytest

from service.io.volume import Volume
from service.preprocess.localiser_inputs import (MIN_GRID_PX, PAD_MULTIPLE, intensity_scale, localiser_inputs,
                                                 target_maps)


def ellipsoid_stack(pixel_mm: float, fov_mm: float = 300.0, thickness_mm: float = 3.0, slices: int = 30,
                    centre_mm: tuple[float, float, float] = (20.0, -35.0, 5.0)) -> tuple[Volume, np.ndarray]:
    """A bright ellipsoid in a dim disc, sampled on a stack of ``pixel_mm`` pixels (the same scene at any size)."""
    n = int(round(fov_mm / pixel_mm))
    xy = (np.arange(n) - (n - 1) / 2) * pixel_mm
    z = (np.arange(slices) - (slices - 1) / 2) * thickness_mm
    x, y, zz = np.meshgrid(xy, xy, z, indexing="ij")
    cx, cy, cz = centre_mm
    brain = ((x - cx) / 45) ** 2 + ((y - cy) / 38) ** 2 + ((zz - cz) / 40) ** 2 <= 1
    body = x ** 2 + (y / 0.8) ** 2 <= 140 ** 2
    image = np.where(brain, 300.0, np.where(body, 100.0, 0.0)).astype(np.float32)
    return Volume(image, np.diag([pixel_mm, pixel_mm, thickness_mm, 1.0])), brain


def test_inputs_are_padded_to_the_grid_and_hold_each_slice_between_its_neighbours() -> None:
    vol, _ = ellipsoid_stack(1.2)
    x, grid = localiser_inputs(vol, 2.5)
    n, c, h, w = x.shape
    assert (n, c) == (30, 3) and h % PAD_MULTIPLE == 0 and w % PAD_MULTIPLE == 0
    assert grid.resampled == (120, 120) and (h, w) == (128, 128)         # 300 mm at 2.5 mm, padded to 16s
    assert np.array_equal(x[1:, 0], x[:-1, 1]) and np.array_equal(x[:-1, 2], x[1:, 1])
    assert np.array_equal(x[0, 0], x[0, 1]) and np.array_equal(x[-1, 2], x[-1, 1])      # the ends repeat
    assert 0 <= x.min() and x.max() <= 2.0


def test_a_mask_goes_to_the_grid_and_back_unchanged() -> None:
    vol, brain = ellipsoid_stack(1.1)
    _, grid = localiser_inputs(vol, 2.5)
    target = target_maps(brain, vol, grid)
    back = grid.to_stack(target) >= 0.5
    assert back.shape == brain.shape
    dice = 2 * (back & brain).sum() / (back.sum() + brain.sum())
    assert dice > 0.97, dice


def test_a_stack_cropped_to_the_head_is_padded_to_the_canvas_and_maps_back() -> None:
    """110 mm of field of view (44 grid pixels) are padded to MIN_GRID_PX: the target stays on the
    image's brain in the padded grid, and the mask comes back to the stack unchanged."""
    vol, brain = ellipsoid_stack(1.1, fov_mm=110.0, centre_mm=(0.0, 0.0, 5.0))
    x, grid = localiser_inputs(vol, 2.5)
    target = target_maps(brain, vol, grid)
    assert grid.resampled == (44, 44) and x.shape[2:] == (MIN_GRID_PX, MIN_GRID_PX) == target.shape[1:]
    inside, outside = x[:, 1][target > 0.9], x[:, 1][(target < 0.1) & (x[:, 1] > 0)]
    assert inside.min() > 0.9 and outside.max() < 0.5                  # the brain (300) is where the target is
    back = grid.to_stack(target) >= 0.5
    assert 2 * (back & brain).sum() / (back.sum() + brain.sum()) > 0.97


def test_a_side_that_ends_in_tissue_is_continued_by_fluid_and_the_target_stays_on_the_brain() -> None:
    """The ellipsoid's stack cut through the body on the side of its first voxel axis (the slices'
    columns): beyond that side, and only there, the grid holds a band of fluid, FLUID_BAND_MM wide;
    the target still lies on the image's brain, and comes back to the stack unchanged."""
    from service.preprocess.localiser_inputs import FLUID_BAND_MM, FLUID_LEVEL

    vol, brain = ellipsoid_stack(1.25, fov_mm=300.0, centre_mm=(-40.0, 0.0, 5.0))
    start = int(np.argwhere(brain)[:, 0].min())                       # the field of view ends at the brain
    cut, cut_brain = vol.region((slice(start, None), slice(None), slice(None))), brain[start:]
    x, grid = localiser_inputs(cut, 2.5)
    (r, c), (h, w) = grid.offset, grid.resampled
    band = int(round(FLUID_BAND_MM / 2.5))
    middle = x[:, 1, r + h // 2]                                         # a row through the middle of each slice
    assert np.allclose(middle[:, c - band:c], FLUID_LEVEL) and np.all(middle[:, c - band - 1] == 0)
    assert np.all(x[:, 1, r - 1, c:c + w] == 0) and np.all(x[:, 1, r + h, c:c + w] == 0)   # top, bottom: air
    assert np.all(x[:, 1, r:r + h, c + w] == 0)                                          # the far side: air
    target = target_maps(cut_brain, cut, grid)
    assert x[:, 1][target > 0.9].min() > 0.9                          # the target is on the brain (300)
    back = grid.to_stack(target) >= 0.5
    assert 2 * (back & cut_brain).sum() / (back.sum() + cut_brain.sum()) > 0.97


def test_the_network_sees_the_same_picture_at_any_pixel_size() -> None:
    fine, _ = ellipsoid_stack(0.6)
    coarse, _ = ellipsoid_stack(1.5)
    a, ga = localiser_inputs(fine, 2.5)
    b, gb = localiser_inputs(coarse, 2.5)
    assert ga.resampled == gb.resampled
    assert np.abs(a - b).mean() < 0.02 and np.abs(a - b).max() < 0.6


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_the_slice_axis_is_the_thick_one_and_maps_back(axis: int) -> None:
    vol, brain = ellipsoid_stack(1.25, fov_mm=200, slices=20)
    array, mask = np.moveaxis(vol.array, 2, axis), np.moveaxis(brain, 2, axis)
    spacing = np.roll([1.25, 1.25, 3.0], axis - 2)
    moved = Volume(np.ascontiguousarray(array), np.diag([*spacing, 1.0]))
    x, grid = localiser_inputs(moved, 2.5)
    assert len(x) == 20 and grid.slice_axis == axis
    back = grid.to_stack(target_maps(mask, moved, grid)) >= 0.5
    assert back.shape == array.shape and (back & mask).sum() > 0.95 * mask.sum()


def test_empty_or_broken_stacks_give_zeros_not_nans() -> None:
    vol = Volume(np.zeros((40, 40, 5), np.float32), np.diag([1.0, 1.0, 3.0, 1.0]))
    x, _ = localiser_inputs(vol, 2.5)
    assert np.all(x == 0)
    bad = np.full((40, 40, 5), np.nan, np.float32)
    bad[5:10, 5:10] = 7.0
    x, _ = localiser_inputs(Volume(bad, vol.affine), 2.5)
    assert np.isfinite(x).all() and x.max() > 0


@pytest.mark.parametrize(("shape", "pixel_mm"), [((4, 320, 300), (1.125, 1.2)), ((3, 40, 56), (2.6, 3.1)), ((2, 64, 64), (0.6, 0.6))])
def test_the_resampling_operators_compute_the_filter_and_zoom_they_replace(shape: tuple, pixel_mm: tuple) -> None:
    """Rows @ image @ cols.T against scipy's Gaussian anti-aliasing then grid-aligned linear zoom."""
    from scipy import ndimage

    from service.geometry.sampling import FWHM_TO_SIGMA
    from service.preprocess.localiser_inputs import _resample

    images = np.random.default_rng(3).random(shape, np.float32)
    factors = np.array(pixel_mm) / 2.5
    sigma = [0.0] + [FWHM_TO_SIGMA * np.sqrt(max(1.0 / f ** 2 - 1.0, 0.0)) for f in factors]
    expected = ndimage.gaussian_filter(images, sigma, mode="nearest", truncate=3.0) if max(sigma) > 0 else images
    size = np.maximum(1, np.round(np.array(shape[1:]) * factors)).astype(int)
    expected = ndimage.zoom(expected, (1.0, *(size / np.array(shape[1:]))), order=1, mode="nearest", grid_mode=True)
    got = _resample(images, pixel_mm, 2.5)
    assert got.shape == expected.shape and got.dtype == np.float32
    assert np.abs(got - expected).max() < 1e-5


def test_maps_go_back_to_the_stack_as_bilinear_interpolation_does() -> None:
    from scipy import ndimage

    from service.preprocess.stack import stack_from_pictures

    vol, _ = ellipsoid_stack(1.1, fov_mm=120, slices=6)
    _, grid = localiser_inputs(vol, 2.5)
    maps = np.zeros((6, *np.add(grid.resampled, 2 * np.array(grid.offset))), np.float32)
    (r, c), (h, w) = grid.offset, grid.resampled
    maps[:, r + 5:r + 30, c + 10:c + 40] = np.random.default_rng(0).random((6, 25, 30))
    scale = np.array(grid.native) / np.array([h, w])
    rows = (np.arange(grid.native[0]) + 0.5) / scale[0] - 0.5
    cols = (np.arange(grid.native[1]) + 0.5) / scale[1] - 0.5
    k, rr, cc = np.meshgrid(np.arange(6), rows, cols, indexing="ij")
    expected = stack_from_pictures(ndimage.map_coordinates(maps[:, r:r + h, c:c + w], [k, rr, cc], order=1,
                                                           mode="nearest"), grid.slice_axis, grid.layout)
    got = grid.to_stack(maps)
    near = got > 0                               # only the box around the non-zero maps is interpolated
    assert np.abs(got - expected)[near].max() < 1e-5 and np.abs(expected[~near]).max() < 1e-3


def test_a_bright_line_does_not_set_the_stacks_intensity_scale() -> None:
    """A saturated column or row (a zipper artefact), wherever it lies, moves the scale by what its
    share of the pixels is worth, as over the whole stack; and the scale does not depend on the
    order the slices are stored in."""
    rng = np.random.default_rng(1)
    clean = rng.gamma(2.0, 100.0, (6, 256, 320)).astype(np.float32)
    reference = intensity_scale(clean)
    for where in (200, 201, 202):                       # every phase of an every-third grid
        for line in (np.s_[:, :, where], np.s_[:, where, :]):
            lined = clean.copy()
            lined[line] = 65535.0
            assert intensity_scale(lined) == pytest.approx(np.percentile(lined, 99.5), rel=0.05)
            assert intensity_scale(lined) < 2 * reference
    assert intensity_scale(clean[::-1]) == reference
    # ... and the network's inputs of a stack so lined are those of the clean stack, not a black stack.
    affine = np.diag([1.1, 1.1, 3.0, 1.0])
    lined = clean.copy()
    lined[:, :, 201] = 65535.0                                        # in step with every third, however laid out
    x_clean, _ = localiser_inputs(Volume(np.moveaxis(clean, 0, -1), affine), 2.5)
    x_lined, _ = localiser_inputs(Volume(np.moveaxis(lined, 0, -1), affine), 2.5)
    assert np.median(x_lined[x_lined > 0]) == pytest.approx(np.median(x_clean[x_clean > 0]), rel=0.25)  # was 1 %


def test_the_localisers_search_is_counted_in_the_field_of_view_not_the_bytes_and_bounded_a_request() -> None:
    """A stack of a scanner's field of view asks a fraction of the request's search; the same bytes
    over a field of view of 900 mm (9 mm pixels) ask 30 times more: three such stacks are searched,
    four are refused (413, naming them) before the localiser runs."""
    from service.core.errors import PayloadTooLarge
    from service.preprocess.localiser_inputs import check_search, search_megapixels

    scanner = Volume(np.zeros((100, 100, 99), np.float32), np.diag([1.125, 1.125, 3.3, 1.0]))
    wide = Volume(np.zeros((100, 100, 99), np.float32), np.diag([9.0, 9.0, 10.0, 1.0]))
    assert search_megapixels(scanner) == 99 * 64 * 64 / 1e6            # padded to the network's canvas
    assert search_megapixels(wide) == 99 * 360 * 360 / 1e6 > 30 * search_megapixels(scanner)
    check_search([("s.nii", scanner)] * 32)                              # a request of 32 scanner stacks
    check_search([("w.nii", wide)] * 3)
    with pytest.raises(PayloadTooLarge, match="stacks a.nii, b.nii, c.nii, d.nii: the localiser would search"):
        check_search([(name, wide) for name in ("a.nii", "b.nii", "c.nii", "d.nii")])
