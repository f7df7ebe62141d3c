"""The slice forward model: equals map_coordinates, recovers known planes, PSF, centring."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from service.geometry import iterators, sampling, se3
from service.geometry.pose import make_pose, slice_pixel_coordinates


def test_sampling_equals_map_coordinates_on_a_random_volume() -> None:
    rng = np.random.default_rng(0)
    vol = rng.random((30, 34, 28)).astype(np.float32)
    aff = np.array([[0.0, -1.2, 0.1, 20.0], [0.9, 0.0, 0.0, -15.0], [0.0, 0.2, 1.5, 4.0], [0, 0, 0, 1]])
    poses = iterators.random_poses(5, rng, tz_max_mm=5.0, centre=aff[:3, :3] @ [15, 17, 14] + aff[:3, 3])
    got = sampling.sample_slices(vol, aff, poses, size=24, pixel_mm=0.7)
    # Independent ground truth: explicit voxel coordinates for each pixel.
    xy = slice_pixel_coordinates(24, 0.7)
    world = np.einsum("bij,rcj->brci", poses[:, :3, :3], np.concatenate([xy, np.zeros((24, 24, 1))], -1))
    world += poses[:, None, None, :3, 3]
    inv = np.linalg.inv(aff)
    vox = np.einsum("ij,brcj->ibrc", inv[:3, :3], world) + inv[:3, 3, None, None, None]
    ref = ndimage.map_coordinates(vol, vox.reshape(3, -1), order=1, mode="constant").reshape(5, 24, 24)
    assert np.abs(got - ref).max() < 1e-5
    assert np.abs(ref).max() > 0.5  # the planes really cut the volume


def _plane_volume() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 1 mm volume whose intensity is the signed distance to a known oblique plane (RAS mm)."""
    n = np.array([1.0, 2.0, 2.0]) / 3.0
    aff = np.eye(4)
    aff[:3, 3] = -32.0
    ijk = np.stack(np.meshgrid(*[np.arange(65.0)] * 3, indexing="ij"), -1)
    world = ijk + aff[:3, 3]
    return (world @ n - 5.0).astype(np.float32), aff, n


def test_sampling_recovers_a_known_plane() -> None:
    vol, aff, n = _plane_volume()
    r = iterators.rotation_to_normal(n[None])[0]
    pose_on = make_pose(r, 5.0 * n)       # the plane distance = 0
    pose_off = make_pose(r, 8.0 * n)      # 3 mm above it
    sl = sampling.sample_slices(vol, aff, np.stack([pose_on, pose_off]), size=20, pixel_mm=1.0)
    np.testing.assert_allclose(sl[0], 0.0, atol=1e-4)
    np.testing.assert_allclose(sl[1], 3.0, atol=1e-4)


def test_thick_slice_psf_averages_through_plane() -> None:
    vol = np.zeros((41, 41, 41), np.float32)
    vol[:, :, 20] = 1.0                                   # a thin sheet at z = 0
    aff = np.eye(4)
    aff[:3, 3] = -20.0
    thin = sampling.sample_slices(vol, aff, np.eye(4)[None], size=8, pixel_mm=1.0)
    thick = sampling.sample_slices(vol, aff, np.eye(4)[None], size=8, pixel_mm=1.0, thickness_mm=4.0,
                                   inplane_fwhm_mm=0.0)
    offsets, w = sampling.psf_offsets(4.0, 0.5)
    assert np.isclose(w.sum(), 1.0) and offsets.max() > 3.0
    assert thin[0, 4, 4] == pytest.approx(1.0)
    # The sheet is 1 voxel thick: a 4 mm FWHM PSF gives about 1 / (4 mm * 1.064) of it.
    assert 0.15 < thick[0, 4, 4] < 0.35


def test_a_thick_slice_is_the_psf_weighted_sum_of_thin_slices_moved_along_its_normal() -> None:
    """Each PSF plane lies ``offset`` mm along the slice's own normal, whatever the pose and the
    volume's (oblique, anisotropic) affine: the thick slice equals the weighted thin slices at
    ``P @ translate(0, 0, offset)``."""
    rng = np.random.default_rng(4)
    vol = rng.random((30, 34, 28)).astype(np.float32)
    aff = np.array([[0.0, -1.2, 0.1, 20.0], [0.9, 0.0, 0.0, -15.0], [0.0, 0.2, 1.5, 4.0], [0, 0, 0, 1]])
    poses = iterators.random_poses(4, rng, tz_max_mm=4.0, centre=aff[:3, :3] @ [15, 17, 14] + aff[:3, 3])
    thick = sampling.sample_slices(vol, aff, poses, size=20, pixel_mm=0.8, thickness_mm=3.0, inplane_fwhm_mm=0.0)
    offsets, weights = sampling.psf_offsets(3.0, 0.5 * float(np.min(np.linalg.norm(aff[:3, :3], axis=0))))
    moved = [poses @ make_pose(np.eye(3), [0.0, 0.0, o]) for o in offsets]
    want = sum(w * sampling.sample_slices(vol, aff, p, size=20, pixel_mm=0.8) for w, p in zip(weights, moved))
    assert len(offsets) > 3 and np.abs(thick - want).max() < 1e-5
    assert np.abs(thick - sampling.sample_slices(vol, aff, poses, size=20, pixel_mm=0.8)).max() > 0.05


def test_mask_centroid_and_recentre_move_the_label_with_the_crop() -> None:
    rng = np.random.default_rng(1)
    mask = np.zeros((60, 60, 60), np.float32)
    mask[35:50, 10:25, 20:40] = 1.0                           # an off-centre box
    aff = np.eye(4)
    aff[:3, 3] = -30.0
    poses = iterators.random_poses(8, rng, tz_max_mm=3.0, centre=[12.0, -12.0, 0.0])
    centred, shift = sampling.centre_on_mask(mask, aff, poses, size=64, pixel_mm=1.0)
    assert np.abs(shift).max() > 0.5
    # Same plane: normals and in-plane axes unchanged, the centre moved within the plane.
    np.testing.assert_allclose(centred[:, :3, :3], poses[:, :3, :3])
    moved = centred[:, :3, 3] - poses[:, :3, 3]
    np.testing.assert_allclose(np.einsum("bi,bi->b", moved, poses[:, :3, 2]), 0.0, atol=1e-9)
    # The mask is now centred in the re-sampled slice.
    new_cent, counts = sampling.mask_centroids(sampling.sample_slices(mask, aff, centred, 64, 1.0), 1.0)
    assert (counts > 0).all()
    assert np.abs(new_cent).max() < 0.75


def test_sampling_agrees_with_pose_composition() -> None:
    """Sampling at g o P equals sampling the volume moved by g^-1 at P (composition ground truth)."""
    rng = np.random.default_rng(2)
    vol = ndimage.gaussian_filter(rng.random((40, 40, 40)), 2).astype(np.float32)
    aff = np.eye(4)
    aff[:3, 3] = -20.0
    g = se3.exp(np.array([0.1, -0.2, 0.15, 2.0, -1.0, 3.0]))
    p = iterators.random_poses(3, rng, tz_max_mm=4.0)
    a = sampling.sample_slices(vol, aff, g @ p, 16, 1.0)
    b = sampling.sample_slices(vol, se3.inverse(g) @ aff, p, 16, 1.0)
    np.testing.assert_allclose(a, b, atol=1e-5)
