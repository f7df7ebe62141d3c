"""Test-time views: each view of a rendered slice is the slice at the pose it maps back from, found
among the 8 candidate poses by rendering alone; MC samples shared among views come back as labels
of the original slice; the estimator shares ``mc_samples`` among the model's views."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from service.geometry import encodings, iterators, sampling, twin
from service.inference.views import VIEW_COUNTS, pose_from_view, sample_views, split_samples, view_images, views
from tests.support.phantoms import mirror_symmetric_volume

PLANE_X = 1.5
SIZE, PIXEL, THICK = 32, 1.0, 3.0
ROT = np.array([[0.0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])    # some quarter turn
FLIP = np.diag([-1.0, 1, 1, 1])


def _render(vol: np.ndarray, aff: np.ndarray, poses: np.ndarray) -> np.ndarray:
    return sampling.sample_slices(vol, aff, poses, size=SIZE, pixel_mm=PIXEL, thickness_mm=THICK)


def _candidates(poses: np.ndarray) -> np.ndarray:
    """``[8, B, 4, 4]``: every pose showing the slices' content turned by quarter turns, or mirrored."""
    mirror = twin.mirror(PLANE_X)
    turns = [np.linalg.matrix_power(ROT, j) for j in range(4)]
    return np.stack([poses @ r for r in turns] + [mirror @ poses @ FLIP @ r for r in turns])


@pytest.fixture(scope="module")
def scene() -> tuple:
    vol, aff = mirror_symmetric_volume(PLANE_X)
    poses = iterators.random_poses(6, np.random.default_rng(4), tz_max_mm=8.0, centre=np.array([PLANE_X, 0, 0]))
    cands = _candidates(poses)
    rendered = np.stack([_render(vol, aff, c) for c in cands])              # [8, B, L, L]
    return poses, cands, rendered


@pytest.mark.parametrize("view", views(8))
def test_each_view_is_the_slice_at_the_pose_it_maps_back_from(scene: tuple, view: tuple[int, bool]) -> None:
    poses, cands, rendered = scene
    k, flip = view
    seen = view_images(rendered[0], k, flip)
    diff = np.abs(rendered - seen[None]).reshape(8, len(poses), -1).max(-1)   # [8, B]
    match = diff.argmin(0)
    assert (diff.min(0) < 1e-4 * np.abs(seen).max()).all()                      # the view is rendered exactly...
    assert (np.sort(diff, 0)[1] > 1e-2).all()                                   # ...by one candidate only
    q = cands[match, np.arange(len(poses))]                                     # the pose of what the view shows
    np.testing.assert_allclose(pose_from_view(q, k, flip, PLANE_X), poses, atol=1e-9)


def test_samples_of_all_views_come_back_as_labels_of_the_original_slices(scene: tuple) -> None:
    """An oracle network that reads the pose off each image: every sample maps back to the truth."""
    poses, cands, rendered = scene
    flat = rendered.reshape(-1, SIZE * SIZE)

    def oracle(label_type: str):  # noqa: ANN202
        def run(images: np.ndarray, n: int) -> np.ndarray:
            idx = np.abs(flat[None] - images.reshape(len(images), 1, -1)).max(-1).argmin(1)
            labels = encodings.encode(label_type, cands.reshape(-1, 4, 4)[idx])
            return np.repeat(labels[:, None], max(n, 1), axis=1)
        return run

    for label_type in ("grid", "anchor", "quaternion"):
        want = encodings.encode(label_type, poses)[:, None]
        for n_views in VIEW_COUNTS:
            got = sample_views(oracle(label_type), rendered[0], 20, label_type, PLANE_X, n_views)
            assert got.shape == (len(poses), 20, want.shape[-1])
            np.testing.assert_allclose(encodings.decode(label_type, got), np.repeat(poses[:, None], 20, 1), atol=1e-6)
        det = sample_views(oracle(label_type), rendered[0], 0, label_type, PLANE_X, 8)    # one pass per view
        assert det.shape == (len(poses), 8, want.shape[-1])


def test_the_samples_are_shared_among_the_views() -> None:
    assert split_samples(100, 8) == [13] * 4 + [12] * 4 and sum(split_samples(7, 8)) == 7
    assert split_samples(3, 8) == [1, 1, 1] and split_samples(0, 4) == [0] * 4
    assert views(1) == [(0, False)] and views(4) == [(k, False) for k in range(4)] and len(set(views(8))) == 8
    with pytest.raises(ValueError):
        views(3)


def test_the_estimator_shares_its_samples_among_the_models_views(tiny_model_path) -> None:  # noqa: ANN001
    from service.inference.estimator import OnnxPoseEstimator
    from service.inference.model_file import load_model

    est = OnnxPoseEstimator(load_model(tiny_model_path))
    x = np.random.default_rng(0).uniform(0, 255, (3, est.info.input_size, est.info.input_size)).astype(np.float32)
    assert est.info.tta_views == 1 and est.sample_labels(x, 10).shape[:2] == (3, 10)
    est.info = dataclasses.replace(est.info, tta_views=8)
    labels = est.sample_labels(x, 10)
    assert labels.shape[:2] == (3, 10) and np.isfinite(labels).all()
    assert est.estimate(x, 0).mean.shape == (3, 4, 4)


def test_grid_labels_map_back_by_reordering_their_points_as_through_the_pose(scene: tuple) -> None:
    from service.inference.views import labels_from_view

    poses = scene[0]
    noisy = encodings.encode("grid", poses) + np.random.default_rng(2).normal(0, 0.5, (len(poses), 192))
    for k, flip in views(8):
        fast = labels_from_view(noisy, "grid", k, flip, PLANE_X)
        via_pose = encodings.encode("grid", pose_from_view(encodings.decode("grid", noisy), k, flip, PLANE_X))
        np.testing.assert_allclose(encodings.decode("grid", fast), encodings.decode("grid", via_pose), atol=1e-9)
        np.testing.assert_allclose(labels_from_view(encodings.encode("grid", poses), "grid", k, flip, PLANE_X),
                                   encodings.encode("grid", pose_from_view(poses, k, flip, PLANE_X)), atol=1e-9)
