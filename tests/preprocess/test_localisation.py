"""What a localisation holds: an uploaded mask's report, and the masks cut from it for the pose network
(the inset against exact distances, on grids of scanners' voxel sizes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from service.preprocess.localisation import POSE_MASK_INSET_MM, Localisation, inset_in_plane


def test_an_uploaded_mask_is_reported_as_such() -> None:
    mask = np.zeros((10, 12, 6), np.uint8)
    mask[2:5, 3:6, 1:4] = 1
    found = Localisation.of(mask, np.array([2.0, 2.0, 4.0]), "mask", 1.0)
    assert found.brain_volume_ml == pytest.approx(27 * 16 / 1000)
    assert found.slices_with_brain == 3
    assert found.report() == {"method": "mask", "brain_volume_ml": 0.4, "confidence": 1.0, "pose_mask_inset_mm": 0.0}


def test_the_inset_removes_exactly_the_pixels_within_its_distance_of_the_outside() -> None:
    """Against exact in-plane Euclidean distances to the nearest outside pixel (outside the array
    counts as outside): random masks on grids of scanners' voxel sizes, touching the array's edge,
    distances that tie with a pixel's, and each axis as the slice axis. In-plane pixels coarser than
    the inset lose the pixels within one of them (by the inset alone they kept every pixel)."""
    rng = np.random.default_rng(0)
    for case in range(60):
        shape = tuple(int(n) for n in rng.integers(5, 30, 3))
        spacing = rng.choice([0.5, 0.5625, 0.7, 1.0, 1.125, 1.6, 3.0, 3.3], 3)
        mask = ndimage.binary_dilation(rng.random(shape) > 0.97, iterations=int(rng.integers(1, 5)))
        mask[:, :2] |= case % 5 == 0
        inset, axis = float(rng.choice([1.0, 2.0, 2.5])), int(rng.integers(0, 3))
        sampling = np.array(spacing, np.float64)
        sampling[axis] = 1e6                                   # the nearest outside within the slice's plane
        distance = ndimage.distance_transform_edt(np.pad(mask, 1), sampling=sampling)[1:-1, 1:-1, 1:-1]
        reach = max(inset, max(spacing[k] for k in range(3) if k != axis))
        np.testing.assert_array_equal(inset_in_plane(mask, spacing, inset, axis), mask & (distance > reach + 1e-9))


@pytest.mark.parametrize("pixel_mm", [2.05, 2.5, 3.0])
def test_pixels_coarser_than_the_inset_still_lose_the_csf_rim(pixel_mm: float) -> None:
    """A low-field scanner's 2-3 mm pixels: the localiser's mask loses its outer pixel in each
    slice's plane (it kept them all: no offset lay within 2 mm), and the answer says 2 mm."""
    spacing = np.array([pixel_mm, pixel_mm, 4.0])
    x, y = np.meshgrid(*[np.arange(40) * pixel_mm] * 2, indexing="ij")
    disc = ((x - 20 * pixel_mm) ** 2 + (y - 20 * pixel_mm) ** 2 <= 30 ** 2)[..., None].repeat(5, axis=2)
    found = Localisation.of(disc, spacing, "network", 0.9)
    inner = found.pose_mask(spacing)
    cross = ndimage.generate_binary_structure(2, 1)[..., None]          # one pixel along each in-plane axis
    assert np.array_equal(inner, ndimage.binary_erosion(np.pad(disc, ((1, 1), (1, 1), (0, 0))), cross)[1:-1, 1:-1])
    assert found.report()["pose_mask_inset_mm"] == POSE_MASK_INSET_MM


def test_the_pose_network_gets_the_localisers_mask_without_its_csf_rim() -> None:
    """An uploaded mask is used as it is; the localiser's (the skull's inside) loses its outer
    POSE_MASK_INSET_MM in each slice's plane, whatever the slice axis, and no slice gains a pixel."""
    spacing = np.array([1.2, 3.0, 1.2])                        # slices along axis 1
    x, y, z = np.meshgrid(*[np.arange(n) * s for n, s in zip((60, 12, 60), spacing)], indexing="ij")
    ball = (x - 36) ** 2 + ((y - 16) * 1.5) ** 2 + (z - 36) ** 2 <= 25 ** 2
    uploaded = Localisation.of(ball, spacing, "mask", 1.0)
    assert uploaded.pose_mask(spacing) is uploaded.mask
    found = Localisation.of(ball, spacing, "network", 0.9)
    inner = found.pose_mask(spacing)
    assert not (inner & ~ball).any() and inner.sum() < ball.sum()
    gone = ball & ~inner
    depth = ndimage.distance_transform_edt(np.pad(ball, ((0, 0), (0, 0), (0, 0))), sampling=[1.2, 1e6, 1.2])
    assert depth[gone].max() <= POSE_MASK_INSET_MM + 1e-6 and depth[inner].min() > POSE_MASK_INSET_MM
    assert np.array_equal(inner, inset_in_plane(ball, spacing, POSE_MASK_INSET_MM, axis=1))
    assert not Localisation.of(np.zeros_like(ball), spacing, "network", 0.0).pose_mask(spacing).any()


def test_a_mask_grown_by_a_margin_holds_exactly_the_voxels_within_that_distance() -> None:
    """Against exact Euclidean distances from the mask, on grids of scanners' voxel sizes (thick
    slices included): every voxel within the margin is added, none beyond it, none removed."""
    from service.preprocess.localisation import grown

    rng = np.random.default_rng(1)
    for _ in range(40):
        shape = tuple(int(n) for n in rng.integers(5, 25, 3))
        spacing = rng.choice([0.5, 0.7, 1.0, 1.125, 1.6, 3.0, 3.3], 3)
        mask = ndimage.binary_dilation(rng.random(shape) > 0.98, iterations=int(rng.integers(0, 3)) or 1)
        margin = float(rng.choice([1.0, 2.0, 3.0, 4.5]))
        distance = ndimage.distance_transform_edt(~mask, sampling=spacing)
        np.testing.assert_array_equal(grown(mask, spacing, margin), distance <= margin)
    assert not grown(np.zeros((4, 4, 4), bool), np.ones(3), 3.0).any()


def _drawn_regions(shape: tuple[int, int, int] = (90, 80, 30)) -> dict[str, np.ndarray]:
    """Regions of interest as viewers draw them around a head (1 x 1 x 3 mm voxels, 150-270 ml)."""
    x, y, z = np.ogrid[:shape[0], :shape[1], :shape[2]]
    box = np.zeros(shape, bool)
    box[10:80, 10:70, 4:26] = True
    disc = ((x - 45) / 35.0) ** 2 + ((y - 40) / 30.0) ** 2 <= 1
    contour = ndimage.binary_fill_holes(ndimage.binary_dilation(disc & (x + y < 110), iterations=2))
    return {"box": box, "elliptic cylinder": box & disc, "contour copied to every slice": box & contour,
            "cylinder along the first axis": box & (((y - 40) / 30.0) ** 2 + ((z - 15) / 11.0) ** 2 <= 1)}


@pytest.mark.parametrize("name", list(_drawn_regions()))
def test_a_shape_drawn_around_the_head_is_a_region_of_interest(name: str) -> None:
    """A box, or any outline drawn in one plane and extruded through the slices, is a region to search."""
    from service.preprocess.localisation import is_region_of_interest

    assert is_region_of_interest(_drawn_regions()[name], np.array([1.0, 1.0, 3.0]))


def test_brain_masks_and_small_drawn_shapes_are_not_regions_of_interest() -> None:
    """Brain-shaped masks (an egg narrower towards the front, cut by motion between slices; the test
    phantoms' masks) are brains, however smooth, and a drawn shape under 100 ml marks the brain."""
    from service.preprocess.localisation import is_region_of_interest
    from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine

    spacing = np.array([1.0, 1.0, 3.0])
    x, y, z = np.ogrid[:90, :80, :30]
    egg = ((x - 45) / (32 - 0.2 * (y - 10))) ** 2 + ((y - 40) / 30.0) ** 2 + ((z - 15) / 11.0) ** 2 <= 1
    moved = np.stack([np.roll(egg[..., k], (k % 3 - 1) * 2, axis=0) for k in range(egg.shape[2])], axis=-1)
    assert not is_region_of_interest(egg, spacing) and not is_region_of_interest(moved, spacing)
    x, y, z = np.ogrid[-60:61, -50:51, -12:13]           # a 38-week brain; stacks that cover its middle only
    big = (x / 55.0) ** 2 + (y / 45.0) ** 2 + ((z * 3.0) / 40.0) ** 2 <= 1
    for slices in (5, 7, 9):
        slab = big[:, :, 12 - slices // 2: 12 - slices // 2 + slices]
        assert slab.sum() * 3 / 1000 >= 100 and not is_region_of_interest(slab, spacing), slices
    for seed in (1, 2, 5):
        brain = phantom_brain(seed)
        for axis in range(3):
            shape = [36, 36, 36]
            shape[axis] = 12
            _, mask = acquire_stack(*brain, stack_affine(axis, np.eye(3), 2.0, 5.0, tuple(shape)), tuple(shape), axis,
                                    np.broadcast_to(np.eye(4), (12, 4, 4)))
            spacing = np.full(3, 2.0)
            spacing[axis] = 5.0
            assert not is_region_of_interest(mask > 0.5, spacing)
    small = _drawn_regions()["elliptic cylinder"][:, :, :8]
    assert small.sum() * 3 / 1000 < 100 and not is_region_of_interest(small, np.array([1.0, 1.0, 3.0]))


def test_the_atlas_brain_masks_are_not_regions_of_interest(atlas_dir: Path) -> None:
    """Every atlas volume's brain mask, on its own grid, is a brain's outline."""
    from service.io.volume import read_volume
    from service.preprocess.localisation import is_region_of_interest

    files = sorted(atlas_dir.rglob("*_mask.nii.gz"))
    assert files
    for f in files:
        volume = read_volume(f)
        assert not is_region_of_interest(np.asarray(volume.array) > 0.5, np.asarray(volume.spacing)), f.name
