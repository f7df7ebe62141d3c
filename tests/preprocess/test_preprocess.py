"""Intensity rescale, slice crop/centre, N4 bias correction."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy import ndimage

from model_export.experiments.localiser_sweep import stored_as
from service.geometry import se3
from service.geometry.pose import make_pose
from service.io.volume import Volume
from service.preprocess.bias import centred_samples, n4_correct, upsample_linear
from service.preprocess.intensity import rescale_0_255
from service.preprocess.slices import preprocess_slices, sample_grid
from service.preprocess.stack import slice_axis_of, slice_images, split_stack, stack_from_pictures
from tests.support.phantoms import phantom_brain


def test_rescale_prunes_one_percent_and_zeroes_outside() -> None:
    rng = np.random.default_rng(0)
    img = rng.normal(100, 10, (2, 50, 50))
    img[0, 0, 0] = 1e6                                         # an outlier does not set the scale
    mask = np.zeros_like(img, bool)
    mask[:, 5:45, 5:45] = True
    out = rescale_0_255(img, mask)
    assert out[~mask].max() == 0 and out[mask].max() == pytest.approx(255.0)
    inside = out[0][mask[0]]
    assert np.mean(inside >= 254.99) == pytest.approx(0.01, abs=0.005)
    assert np.median(inside) == pytest.approx(127.5, abs=10)


def test_preprocess_centres_the_mask_and_handles_anisotropic_pixels() -> None:
    img = np.zeros((1, 60, 40), np.float32)
    img[0, 40:50, 5:15] = np.arange(100).reshape(10, 10) + 1
    mask = img > 0
    out = preprocess_slices(img, mask, (0.5, 1.0), 32, 1.0)   # rows 0.5 mm, columns 1 mm
    cx = ((5 + 14) / 2 - 19.5) * 1.0
    cy = ((40 + 49) / 2 - 29.5) * 0.5
    np.testing.assert_allclose(out.centroid_mm[0], [cx, cy], atol=1e-9)
    rows, cols = np.nonzero(out.inputs[0] > 0)
    assert abs(rows.mean() - 15.5) < 0.6 and abs(cols.mean() - 15.5) < 0.6
    assert 0.0 < out.mask_fraction[0] < 0.1
    np.testing.assert_allclose(out.input_from_network()[0][:2, 3], [cx, cy])


@pytest.mark.parametrize("blur", [False, True])
def test_a_slice_whose_pixels_in_its_mask_are_all_alike_has_no_region_to_pose(blur: bool) -> None:
    """A blank (or saturated) slice under a mask shows nothing: ``empty``, not a pose of zeros."""
    img = np.zeros((3, 40, 40), np.float32)
    img[0, 10:30, 10:30] = np.arange(400).reshape(20, 20) + 1            # an image
    img[2, 10:30, 10:30] = 700.0                                          # saturated
    mask = np.zeros(img.shape, bool)
    mask[:, 10:30, 10:30] = True
    out = preprocess_slices(img, mask, (2.0, 2.0) if blur else (1.0, 1.0), 32, 1.0 if not blur else 3.0)
    assert out.mask_fraction[0] > 0.1 and out.mask_fraction[1] == out.mask_fraction[2] == 0.0
    assert not out.inputs[1:].any()


def test_slice_axis_is_largest_spacing_ties_last() -> None:
    assert slice_axis_of([1.0, 3.0, 1.0]) == 1
    assert slice_axis_of([2.0, 2.0, 2.0]) == 2
    assert slice_axis_of([3.0, 3.0, 1.0]) == 1


def test_split_stack_is_vectorised_and_right_handed() -> None:
    aff = np.diag([-0.8, 0.8, 4.0, 1.0])                     # left-handed voxel axes
    vol = Volume(np.random.default_rng(0).random((10, 12, 5)).astype(np.float32), aff)
    s = split_stack(vol, np.ones((10, 12, 5), bool))
    assert s.images.shape == (5, 12, 10)
    np.testing.assert_array_equal(s.images[2], vol.array[::-1, :, 2].T)    # columns along +x: the stored axis reversed
    world_from_slice = aff @ np.linalg.inv(s.slice_from_voxel[2])
    assert np.linalg.det(world_from_slice[:3, :3]) == pytest.approx(1.0)   # a rigid map


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_stack_stored_with_its_in_plane_voxels_in_any_order_gives_the_same_pictures_and_slice_frames(seed: int) -> None:
    """Rows reversed, columns reversed, the two axes swapped (the eight ways a file can store a
    slice): the same pictures, masks and slice frames in the world, so the network sees one stack."""
    rng = np.random.default_rng(seed)
    rot = se3.so3_exp(rng.normal(0, 0.6, 3))                     # an oblique stack, any handedness of storage
    aff = make_pose(rot, rng.uniform(-50, 50, 3)) @ np.diag([0.9, 1.1, 3.0, 1.0])
    vol = Volume(rng.random((9, 11, 6)).astype(np.float32), aff)
    mask = rng.random((9, 11, 6)) > 0.4
    ref = split_stack(vol, mask)
    world = aff @ np.linalg.inv(ref.slice_from_voxel)
    for flip0, flip1, swap in itertools.product([False, True], repeat=3):
        other = stored_as(vol, flip0, flip1, swap)
        s = split_stack(other, np.asarray(stored_as(Volume(mask, aff), flip0, flip1, swap).array))
        np.testing.assert_array_equal(s.images, ref.images)
        np.testing.assert_array_equal(s.masks, ref.masks)
        assert s.pixel_mm == ref.pixel_mm
        np.testing.assert_allclose(other.affine @ np.linalg.inv(s.slice_from_voxel), world, atol=1e-9)
        np.testing.assert_array_equal(s.to_stack(s.masks), stored_as(Volume(mask, aff), flip0, flip1, swap).array)


def test_slice_masks_go_back_to_the_stacks_voxels_along_any_slice_axis() -> None:
    mask = np.random.default_rng(1).random((6, 7, 8)) > 0.5
    for axis in range(3):
        spacing = [1.0, 1.0, 1.0]
        spacing[axis] = 3.0
        s = split_stack(Volume(mask.astype(np.float32), np.diag(spacing + [1.0])), mask)
        assert s.slice_axis == axis
        np.testing.assert_array_equal(s.to_stack(s.masks), mask)
        images, _, layout = slice_images(mask, np.diag(spacing + [1.0]), axis)
        np.testing.assert_array_equal(stack_from_pictures(images, axis, layout), mask)
        np.testing.assert_array_equal(images, s.masks)                 # the localiser's pictures are the pose network's


def biased_phantom(strength: float = 0.5) -> tuple[Volume, np.ndarray, np.ndarray]:
    img, mask, _ = phantom_brain(1, shape=(64, 72, 20), spacing=1.2)
    aff = np.diag([1.2, 1.2, 3.0, 1.0])
    x = np.linspace(-1, 1, 64)[:, None, None]
    y = np.linspace(-1, 1, 72)[None, :, None]
    field = np.exp(strength * (x + 0.5 * y**2))
    return Volume((img * field).astype(np.float32), aff), mask > 0.5, img


def test_n4_removes_a_smooth_bias_field_and_the_shrunk_fit_equals_the_full_resolution_one() -> None:
    """The default fit (shrunk x4 / to >= 8 mm pixels) corrects as the full-resolution fit does
    (its speed is a benchmark matter: ``benchmarks/predict_bench.py`` reports the N4 stage)."""
    vol, mask, clean = biased_phantom()
    tissue = mask & (clean > 60) & (clean < 120)             # the uniform 'parenchyma'
    cv = lambda a: a[tissue].std() / a[tissue].mean()       # noqa: E731
    fast = n4_correct(vol, mask)
    full = n4_correct(vol, mask, shrink=1, fit_spacing_mm=0.0)
    assert cv(fast) < 0.6 * cv(vol.array)
    assert np.corrcoef(fast[mask], full[mask])[0, 1] > 0.98


def test_the_fit_grid_samples_the_region_centred_and_maps_back_onto_its_source() -> None:
    """N4's fit grid: samples ``factor`` voxels apart centred on each axis (a voxel's value where the
    centre falls on one, two voxels' mean between them), the same samples for an axis stored the other
    way, and each source voxel's place in it such that a linear ramp, shrunk and interpolated back, is
    itself; beyond the grid the value is the interpolant's at the nearest point of the grid."""
    rng = np.random.default_rng(3)
    factors = [4, 7, 1]                 # 23 voxels: samples at 3, 7, ..., 19; 31: at 4.5, 11.5, 18.5, 25.5
    values = rng.random((23, 31, 9))
    small, at = centred_samples(values, factors)
    assert small.shape == (5, 4, 9)
    np.testing.assert_allclose(small[:, 0], values[3:20:4, 4:6].mean(axis=1), rtol=1e-6)
    reversed_small, _ = centred_samples(values[::-1, ::-1, ::-1], factors)
    np.testing.assert_allclose(reversed_small[::-1, ::-1, ::-1], small, rtol=1e-6)
    x, y, z = np.meshgrid(*(np.arange(n, dtype=np.float64) for n in values.shape), indexing="ij")
    ramp = 0.3 * x - 0.2 * y + 0.5 * z
    back = upsample_linear(centred_samples(ramp, factors)[0], at)
    inside = np.ix_(*[(c >= 0) & (c <= n - 1) for c, n in zip(at, small.shape)])
    assert all(((c < 0) | (c > n - 1)).any() for c, n in zip(at[:2], small.shape))   # the test reaches beyond
    np.testing.assert_allclose(back[inside], ramp[inside], atol=1e-5)
    clamped = [np.clip(c, 0, n - 1) for c, n in zip(at, small.shape)]
    np.testing.assert_allclose(back, upsample_linear(centred_samples(ramp, factors)[0], clamped), atol=1e-7)


def test_the_inputs_do_not_depend_on_the_empty_field_of_view_around_the_masks() -> None:
    """The same slices inside a larger field of view (padded equally on both sides, so the slice
    frame stays put) give the same network inputs, centroids and mask fractions: only the masks'
    surroundings within the anti-aliasing kernel's reach count. Fine pixels (anti-aliased) and
    coarse ones (not) alike."""
    rng = np.random.default_rng(4)
    for pixel in ((0.5, 0.6), (1.5, 1.5)):
        img = rng.random((5, 60, 70)).astype(np.float32) * 100
        yy, xx = np.mgrid[:60, :70]
        mask = np.stack([(yy - 28 - k) ** 2 / 15 ** 2 + (xx - 40) ** 2 / 12 ** 2 < 1 for k in range(5)])
        mask[2] = False                                            # an empty slice too
        small = preprocess_slices(img, mask, pixel, 32, 1.25)
        pad = ((0, 0), (40, 40), (30, 30))
        large = preprocess_slices(np.pad(img, pad, constant_values=500.0), np.pad(mask, pad), pixel, 32, 1.25)
        np.testing.assert_allclose(large.inputs, small.inputs, atol=1e-3)
        np.testing.assert_allclose(large.centroid_mm, small.centroid_mm, atol=1e-9)
        np.testing.assert_array_equal(large.mask_fraction, small.mask_fraction)
        assert small.inputs[2].max() == 0 and small.inputs[0].max() > 100


def test_separable_sampling_equals_scipy_trilinear_sampling_at_the_same_points() -> None:
    """The network's input sampler blends rows, then columns; scipy samples each point from eight."""
    rng = np.random.default_rng(3)
    images = rng.random((5, 37, 41)).astype(np.float32)
    rows = rng.uniform(-4.0, 40.0, (5, 1)) + 0.9 * np.arange(24)
    cols = rng.uniform(-4.0, 44.0, (5, 1)) + 1.1 * np.arange(24)
    rows[0, :3], cols[1, :3] = [0.0, 36.0, -1e-9], [0.0, 40.0, 40.0 + 1e-9]       # the edges, just in and out
    got = sample_grid(images, rows, cols)
    b = np.broadcast_to(np.arange(5.0)[:, None, None], (5, 24, 24))
    points = np.stack([b, np.broadcast_to(rows[:, :, None], b.shape), np.broadcast_to(cols[:, None, :], b.shape)])
    want = ndimage.map_coordinates(images, points.reshape(3, -1), order=1, mode="constant", prefilter=False)
    assert np.abs(got - want.reshape(b.shape)).max() < 1e-5
    assert (got == 0).any() and (got > 0).mean() > 0.5                            # both cases exercised
