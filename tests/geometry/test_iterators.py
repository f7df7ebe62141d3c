"""Pose iterators: counts, bounds, and the evenness of the Fibonacci sphere."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from service.geometry import iterators


def _is_rotation(r: np.ndarray) -> bool:
    return np.allclose(r @ np.swapaxes(r, -1, -2), np.eye(3), atol=1e-10) and np.allclose(np.linalg.det(r), 1)


def test_euler_grid_matches_the_paper() -> None:
    poses = iterators.euler_grid(tz_max_mm=40.0, tz_step_mm=2.0, centre=(1.0, 2.0, 3.0))
    assert poses.shape == (10**3 * 41, 4, 4)
    assert _is_rotation(poses[:, :3, :3])
    # t = centre + Tz * normal, with Tz in [-40, 40] in 2 mm steps.
    tz = np.einsum("ni,ni->n", poses[:, :3, 3] - [1, 2, 3], poses[:, :3, 2])
    np.testing.assert_allclose(np.unique(np.round(tz, 9)), np.arange(-40, 41, 2))


def test_fibonacci_normals_follow_the_formula_and_cover_the_sphere_evenly() -> None:
    n = iterators.fibonacci_normals(300)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)
    np.testing.assert_allclose(n[:, 2], 1 - (2 * np.arange(300) + 1) / 300)
    d, _ = cKDTree(n).query(n, k=2)
    nn_deg = np.rad2deg(2 * np.arcsin(d[:, 1] / 2))
    # The paper: ~8 degrees between neighbours; evenly: small spread, far below random points'.
    assert 7.0 < nn_deg.mean() < 13.0
    rnd = np.random.default_rng(0).normal(size=(300, 3))
    rnd /= np.linalg.norm(rnd, axis=1, keepdims=True)
    dr, _ = cKDTree(rnd).query(rnd, k=2)
    assert nn_deg.std() / nn_deg.mean() < 0.1 < np.std(dr[:, 1]) / np.mean(dr[:, 1])
    # Hemisphere balance and zero resultant.
    assert abs((n[:, 0] > 0).mean() - 0.5) < 0.03 and np.linalg.norm(n.mean(0)) < 0.01


def test_rotation_to_normal_maps_z_onto_each_normal_including_antipodes() -> None:
    normals = np.r_[iterators.fibonacci_normals(50), [[0, 0, -1.0], [0, 0, 1.0]]]
    r = iterators.rotation_to_normal(normals)
    assert _is_rotation(r)
    np.testing.assert_allclose(r[:, :, 2], normals, atol=1e-12)


def test_fibonacci_grid_counts_and_inplane_range() -> None:
    poses = iterators.fibonacci_grid(n_normals=300, n_inplane=10, tz_max_mm=40, tz_step_mm=4)
    assert poses.shape == (300 * 10 * 21, 4, 4)
    assert _is_rotation(poses[:, :3, :3])


def test_random_poses_stay_within_bounds() -> None:
    rng = np.random.default_rng(0)
    p = iterators.random_poses(2000, rng, tz_max_mm=iterators.tz_limit(120.0))
    tz = np.einsum("ni,ni->n", p[:, :3, 3], p[:, :3, 2])
    assert np.abs(tz).max() <= 0.35 * 120 + 1e-9
    assert _is_rotation(p[:, :3, :3])
    # Normals uniform on the sphere: mean close to zero.
    assert np.linalg.norm(p[:, :3, 2].mean(0)) < 0.1
