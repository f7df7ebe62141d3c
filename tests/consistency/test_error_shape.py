"""The shape of the network's error: anatomical axes, error coordinates, the depth gain."""

from __future__ import annotations

import numpy as np

from service.consistency.error_shape import anatomical_axes, error_coordinates, error_shape
from service.geometry import se3
from service.geometry.anchors import ANCHOR_HALF_SIZE_MM
from service.geometry.iterators import random_rotations
from service.geometry.pose import make_pose


def test_anatomical_x_is_the_in_plane_direction_nearest_left_right() -> None:
    planes = random_rotations(500, np.random.default_rng(0))
    r = anatomical_axes(planes)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    np.testing.assert_allclose(r[:, :, 2], np.tile([0.0, 0.0, 1.0], (500, 1)), atol=1e-12)   # the normal is kept
    axes = planes @ r
    normal = planes[:, :, 2]
    for ref, k in ((np.array([1.0, 0, 0]), 0), (np.array([0, 1.0, 0]), 1)):
        proj = ref - (normal @ ref)[:, None] * normal                  # the reference projected on each plane
        sagittal = np.linalg.norm(planes[:, 0, :2], axis=1) < 0.5
        pick = ~sagittal if k == 0 else sagittal
        unit = proj[pick] / np.linalg.norm(proj[pick], axis=1, keepdims=True)
        np.testing.assert_allclose(np.einsum("ij,ij->i", axes[pick, :, 0], unit), 1.0, atol=1e-9)


def test_error_coordinates_recover_a_known_error_in_anatomical_axes() -> None:
    rng = np.random.default_rng(1)
    true = make_pose(random_rotations(50, rng), rng.normal(0, 30, (50, 3)))
    w, t = rng.normal(0, 0.05, (50, 3)), rng.normal(0, 3, (50, 3))        # rad, mm, along the anatomical axes
    r = anatomical_axes(true[:, :3, :3])
    err = make_pose(r @ se3.so3_exp(w) @ np.swapaxes(r, 1, 2), np.einsum("nij,nj->ni", r, t))
    got = error_coordinates(true @ err, true)
    np.testing.assert_allclose(got, np.concatenate([w * ANCHOR_HALF_SIZE_MM, t], axis=1), atol=1e-9)


def test_error_shape_is_robust_to_slices_the_network_cannot_place() -> None:
    rng = np.random.default_rng(2)
    clean = rng.normal(0, [2.0, 1.0, 0.5, 0.2, 0.3, 1.5], (2000, 6))
    dirty = clean.copy()
    dirty[:200] = rng.normal(0, 60.0, (200, 6))                              # a tenth far off in every coordinate
    expected = rng.uniform(0.5, 2.0, 2000)
    a, b = error_shape(clean * expected[:, None], expected), error_shape(dirty * expected[:, None], expected)
    np.testing.assert_allclose(a.mean(), 1.0)
    np.testing.assert_allclose(a / a[0], np.array([4.0, 1.0, 0.25, 0.04, 0.09, 2.25]) / 4.0, rtol=0.15)
    np.testing.assert_allclose(b / b[0], a / a[0], rtol=0.3, atol=0.01)


def test_a_coordinate_without_error_keeps_a_share_a_model_can_hold() -> None:
    """A network whose answers hardly vary along one coordinate (a short calibration): that coordinate
    keeps a positive share, written and read back as six positive numbers (the model's metadata)."""
    from service.inference.model_file import _shape

    coords = np.random.default_rng(3).normal(0, [3.0, 1.0, 1.0, 0.5, 0.5, 1e-5], (500, 6))
    shape = error_shape(coords, np.ones(500))
    assert shape[5] > 0 and np.isclose(shape.mean(), 1.0)
    assert _shape(",".join(f"{x:.4g}" for x in shape)) is not None     # as model_export.spread writes it
