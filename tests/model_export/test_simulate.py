"""Training-slice simulation conforms to the service's forward model and preprocessing."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

from model_export.atlas import load_volumes, split
from model_export.simulate import (
    Acquisition,
    SimulationConfig,
    SliceSimulator,
    dress,
    sample_slices_torch,
    shading_ball,
    wobble_masks,
)
from service.geometry import iterators, sampling
from service.preprocess.intensity import rescale_0_255


def test_torch_sampler_equals_the_numpy_forward_model(phantom_atlas: Path) -> None:
    vol = load_volumes(["STA30"], phantom_atlas)[0]
    rng = np.random.default_rng(0)
    poses = iterators.random_poses(6, rng, tz_max_mm=10.0, centre=vol.centre)
    ref = sampling.sample_slices(vol.image, vol.affine, poses, 40, 1.3)
    got = sample_slices_torch(torch.from_numpy(vol.image)[None, None], vol.affine, poses, 40, 1.3)[:, 0].numpy()
    assert np.abs(ref).max() > 50
    np.testing.assert_allclose(got, ref, atol=1e-3)
    offsets, w = sampling.psf_offsets(3.0, 0.8)
    thick = sample_slices_torch(torch.from_numpy(vol.image)[None, None], vol.affine, poses, 40, 1.3, offsets, w)
    ref_thick = sampling.sample_slices(vol.image, vol.affine, poses, 40, 1.3, thickness_mm=3.0, inplane_fwhm_mm=0.0)
    np.testing.assert_allclose(thick[:, 0].numpy(), ref_thick, atol=1e-3)


def test_training_slice_is_the_service_preprocessing_and_its_label_re_renders_it(phantom_atlas: Path) -> None:
    """A clean simulated input equals the slice rendered at its label pose on the network grid.

    This is the crop/centre contract: the label is the atlas pose of the CENTRED network input.
    """
    vol = load_volumes(["STA30"], phantom_atlas)[0]
    cfg = SimulationConfig(size=48, pixel_mm=1.5, acq_pixel_mm=(1.5, 1.5), thickness_mm=(0.01, 0.01), noise=(0, 0),
                           bias=0.0, gamma=(1, 1), void_probability=0.0, mask_threshold=(0.5, 0.5), mask_blur_px=0.01)
    sim = SliceSimulator([vol], cfg)
    rng = np.random.default_rng(1)
    poses = sim.sample_poses(vol, 8, rng)
    # Shift the acquisition planes in-plane so that the brain is NOT centred in the acquired field.
    poses = sampling.recentre(poses, rng.uniform(-15, 15, size=(8, 2)))
    img, mask = sim.acquire(0, poses, 1.5, 0.01)
    batch = sim.finish(Acquisition(img, mask, poses, 1.5, 0.01, 1.0, "STA30"), rng)
    assert len(batch.inputs) == 8
    rendered = sampling.sample_slices(vol.image, vol.affine, batch.poses, 48, 1.5)
    rmask = sampling.sample_slices(vol.mask, vol.affine, batch.poses, 48, 1.5) > 0.5
    expected = rescale_0_255(rendered, rmask)
    # In-plane blur of the acquisition (1.2 px FWHM) and one extra interpolation separate the two.
    inside = rmask & (batch.inputs > 0)
    diff = np.abs(batch.inputs - expected)[inside]
    assert np.median(diff) < 6.0, np.median(diff)
    # The label moved with the crop: the mask is centred in the re-rendered slice.
    cent, _ = sampling.mask_centroids(rmask.astype(np.float32), 1.5)
    assert np.abs(cent).max() < 1.5
    # ... whereas the acquisition planes themselves were off-centre.
    cent0, _ = sampling.mask_centroids(sampling.sample_slices(vol.mask, vol.affine, poses, 48, 1.5), 1.5)
    assert np.abs(cent0).max() > 5.0


def test_batches_have_labels_and_realistic_ranges(phantom_atlas: Path) -> None:
    train, val = split(phantom_atlas)
    assert set(val).isdisjoint(train) and any(v.startswith("SB") for v in val) and any(v.startswith("STA") for v in val)
    sim = SliceSimulator(load_volumes(train, phantom_atlas), SimulationConfig(size=48, pixel_mm=2.0))
    b = sim.batch(32, np.random.default_rng(2), volumes_per_batch=2)
    assert b.inputs.shape[1:] == (48, 48) and len(b.inputs) == len(b.poses) > 16
    assert b.inputs.min() >= 0 and b.inputs.max() <= 255 and b.inputs.max() > 200
    r = b.poses[:, :3, :3]
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-9)
    assert (b.thickness_mm >= 2.0).all() and (b.thickness_mm <= 4.5).all()


def test_wobbled_masks_move_the_boundary_by_up_to_their_amplitude_and_stay_one_piece() -> None:
    yy, xx = np.mgrid[:96, :96]
    disk = (yy - 48) ** 2 + (xx - 48) ** 2 <= 30 ** 2
    masks = np.repeat(disk[None], 40, axis=0)
    cfg = SimulationConfig(mask_wobble_share=0.5, mask_wobble_px=(6.0, 6.0))
    out = wobble_masks(masks, cfg, np.random.default_rng(3))
    changed = (out != masks).any(axis=(1, 2))
    assert 10 <= changed.sum() <= 30                      # about half the slices
    for m in out[changed]:
        assert ndimage.label(m)[1] == 1
        radius = np.hypot(*(np.argwhere(m & ~ndimage.binary_erosion(m)) - 48).T)
        assert radius.min() < 28 or radius.max() > 32      # bites or bulges of a few pixels
        assert 30 - 6 * 4.5 < radius.min() and radius.max() < 30 + 6 * 4.5 + 1
    rng = np.random.default_rng(3)
    np.testing.assert_array_equal(wobble_masks(masks, SimulationConfig(), rng), masks)
    # the option off draws nothing: the stream goes on as without it (the validation slices stay the same)
    assert rng.random() == np.random.default_rng(3).random()


def test_dressed_slices_keep_the_brain_and_show_csf_skull_and_tissue_by_distance(phantom_atlas: Path) -> None:
    vol = load_volumes(["STA30"], phantom_atlas)[0]
    sim = SliceSimulator([vol], SimulationConfig(surroundings_share=1.0))
    rng = np.random.default_rng(2)
    poses = iterators.random_poses(4, rng, tz_max_mm=5.0, centre=vol.centre)
    img, mask = sim.acquire(0, poses, 1.2, 2.0)
    distance = sim.distance(0, poses, 1.2)
    assert np.all(distance[mask > 0.99] < 0.6) and np.all(distance[mask < 0.01] > -0.6)
    assert distance.max() > 15.0                          # beyond the atlas's tight crop, held there
    dressed = dress(img, mask, distance, np.random.default_rng(0), share=1.0)
    inside = mask >= 1.0
    np.testing.assert_array_equal(dressed[inside], img[inside])
    added = dressed - img
    for k in range(4):
        csf = added[k][(distance[k] > 0.2) & (distance[k] < 0.5)].mean()     # within every CSF layer
        skull_window = added[k][(distance[k] > 0.5) & (distance[k] < 4.5)]  # holds >= 1 mm of skull
        far = distance[k] > 14.0                                              # beyond every layer: tissue
        assert skull_window.min() < 0.5 * csf
        assert dressed[k][far].mean() > 10.0 and img[k][far].max() < 1e-6


def test_an_offset_dilates_wobbled_masks_by_about_its_size() -> None:
    yy, xx = np.mgrid[:96, :96]
    disk = (yy - 48) ** 2 + (xx - 48) ** 2 <= 30 ** 2
    masks = np.repeat(disk[None], 8, axis=0)
    out = wobble_masks(masks, SimulationConfig(mask_wobble_share=1.0, mask_offset_px=(3.0, 3.0)),
                       np.random.default_rng(0))
    radius = np.sqrt(out.sum(axis=(1, 2)) / np.pi)
    np.testing.assert_allclose(radius, 33.0, atol=0.6)


def test_the_padded_distance_map_samples_the_brains_own_distance_at_each_pixels_atlas_point(phantom_atlas: Path) -> None:
    """Each slice pixel, carried to atlas mm by its pose and to the unpadded volume's voxels by the
    atlas's affine, has there (trilinear) the signed distance the simulator sampled from its padded
    map: the padded map's affine is the crop's, moved by the pad."""
    from scipy import ndimage as nd

    from model_export.atlas import signed_distance
    from service.geometry.pose import slice_pixel_coordinates

    vol = load_volumes(["STA30"], phantom_atlas)[0]
    sim = SliceSimulator([vol], SimulationConfig(surroundings_share=1.0))
    poses = iterators.random_poses(3, np.random.default_rng(4), tz_max_mm=5.0, centre=vol.centre)
    distance = sim.distance(0, poses, 1.3)
    size = distance.shape[1]
    xy = slice_pixel_coordinates(size, 1.3)
    plane = np.concatenate([xy, np.zeros((size, size, 1)), np.ones((size, size, 1))], axis=-1)     # [L, L, 4]
    voxel = np.einsum("ij,bjk,rck->brci", np.linalg.inv(vol.affine), poses, plane)[..., :3]
    spacing = np.sqrt((vol.affine[:3, :3] ** 2).sum(0))
    own = nd.map_coordinates(signed_distance(vol.mask > 0.5, spacing), np.moveaxis(voxel, -1, 0), order=1, mode="nearest")
    inside_crop = np.all((voxel > 1) & (voxel < np.array(vol.mask.shape) - 2), axis=-1)
    near_brain = inside_crop & (own < 2.0)          # within the crop, where the crop cuts no distance short
    assert near_brain.sum() > 100
    np.testing.assert_allclose(distance[near_brain], own[near_brain], atol=0.05)


def test_shading_ball_darkens_a_disc_as_drawn_and_costs_no_draw_when_off() -> None:
    cfg = SimulationConfig(size=96, pixel_mm=1.25, shading_ball_probability=1.0, shading_ball_radius_mm=(20.0, 20.0),
                           shading_ball_gain=(0.4, 0.4), shading_ball_edge_mm=(1.0, 1.0))
    gain = shading_ball(6, 96, cfg, np.random.default_rng(0))
    px = 120.0 / 95                                                   # the grid's spacing over 120 mm
    for g in gain:
        dark = g < 0.7
        assert abs(g.min() - 0.4) < 0.01 and g.max() > 0.99
        assert abs(np.sqrt(dark.sum() / np.pi) * px - 20.0) < 2.0       # a disc of 20 mm radius
        centre = (np.argwhere(dark).mean(axis=0) - 47.5) * px
        assert np.abs(centre).max() <= 30.0 + px                        # about a point near the brain's centre
    a, b = np.random.default_rng(3), np.random.default_rng(3)
    assert np.all(shading_ball(4, 32, SimulationConfig(), a) == 1.0)    # off by default
    assert a.random() == b.random()                                     # and the stream of draws untouched
