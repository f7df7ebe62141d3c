"""Grid labels: encode/decode, the weighted Kabsch fit, and the label checked against rendered slices."""

from __future__ import annotations

import numpy as np

from service.geometry import encodings, grid, iterators, sampling, se3, twin
from service.geometry.pose import slice_pixel_coordinates


def _poses(n: int, seed: int = 0) -> np.ndarray:
    return iterators.random_poses(n, np.random.default_rng(seed), tz_max_mm=30.0, centre=np.array([2.0, -5.0, 8.0]))


def test_round_trip_and_registered_encoding() -> None:
    poses = _poses(40)
    lab = encodings.encode("grid", poses)
    assert lab.shape == (40, 3 * grid.GRID_SIZE**2)
    assert np.allclose(encodings.decode("grid", lab), poses, atol=1e-9)
    # the centre of the plane is the mean of the (symmetric) grid points
    assert np.allclose(lab.reshape(40, -1, 3).mean(1), poses[:, :3, 3])


def test_noisy_and_degenerate_predictions_decode_to_proper_rotations() -> None:
    rng = np.random.default_rng(1)
    lab = encodings.encode("grid", _poses(30)) + rng.normal(scale=15.0, size=(30, 192))
    lab[0] = np.repeat(rng.normal(size=(1, 3)), 64, 0).ravel()             # all points equal
    lab[1] = (np.linspace(0, 1, 64)[:, None] * [1.0, 2.0, 3.0]).ravel()     # collinear
    lab[2, 5] = np.nan                                                       # not finite
    rot = grid.decode(lab)[:, :3, :3]
    assert np.all(np.isfinite(rot))
    assert np.allclose(np.linalg.det(rot), 1.0)
    assert np.allclose(rot.transpose(0, 2, 1) @ rot, np.eye(3), atol=1e-9)


def test_kabsch_recovers_noise_free_pose_and_weights_silence_outliers() -> None:
    pose = se3.exp(np.array([0.3, -2.0, 0.7, 10.0, 4.0, -6.0]))
    pts = grid.encode(pose).reshape(64, 3)
    bad = pts.copy()
    bad[:5] += 80.0                                                          # five wild points
    assert not np.allclose(grid.kabsch(grid.TEMPLATE, bad), pose, atol=1e-3)
    w = np.ones(64)
    w[:5] = 0.0
    assert np.allclose(grid.kabsch(grid.TEMPLATE, bad, w), pose, atol=1e-9)
    # least squares: the fit to symmetric noise is closer than the noisy points are
    noisy = pts + np.random.default_rng(2).normal(scale=3.0, size=pts.shape)
    fit = grid.encode(grid.decode(noisy.ravel())).reshape(64, 3)
    assert np.linalg.norm(fit - pts, axis=1).mean() < np.linalg.norm(noisy - pts, axis=1).mean() / 3


def test_the_planar_closed_form_is_the_svd_fit() -> None:
    """The MC statistics' path (shared planar template, equal weights: closed form) gives the SVD fit of
    the general path, noisy labels and all; collinear ones fall back to the SVD."""
    rng = np.random.default_rng(3)
    lab = encodings.encode("grid", _poses(200)).reshape(200, 64, 3) + rng.normal(scale=25.0, size=(200, 64, 3))
    lab[7] = np.linspace(0, 1, 64)[:, None] * [1.0, 2.0, 3.0]
    closed = grid.kabsch(grid.TEMPLATE, lab)
    general = grid.kabsch(grid.TEMPLATE, lab, np.ones((200, 64)))               # weighted: the SVD path
    rest = np.arange(200) != 7                                                  # collinear: no unique fit
    assert np.allclose(closed[rest], general[rest], atol=1e-9)
    assert np.isclose(np.linalg.det(closed[7, :3, :3]), 1.0)
    _, fitted = grid._planar_rotation(np.swapaxes(np.swapaxes(grid.TEMPLATE - grid.TEMPLATE.mean(0), 0, 1) @ lab, -1, -2)[..., :2])
    assert not fitted[7] and fitted.sum() == 199


def test_grid_label_is_where_the_rendered_slice_samples_the_volume() -> None:
    """Against simulated ground truth: a volume whose intensity is atlas x (then y, then z)."""
    n = 121
    aff = np.eye(4)
    aff[:3, 3] = -60.0
    coords = np.stack(np.meshgrid(*[np.arange(n) - 60.0] * 3, indexing="ij"), -1)
    size, pixel = 57, 15.0 / 7.0          # pixel centres at multiples of 15/7 mm: the 8 x 8 grid is among them
    xy = slice_pixel_coordinates(size, pixel)
    pick = [int(np.argmin(np.abs(xy[0, :, 0] - u))) for u in np.linspace(-60, 60, 8)]
    assert np.allclose(xy[0, pick, 0], np.linspace(-60, 60, 8))
    poses = iterators.random_poses(6, np.random.default_rng(3), tz_max_mm=5.0, centre=np.zeros(3))
    poses[:, :3, 3] *= 0.1                # keep the plane inside the volume
    lab = encodings.encode("grid", poses).reshape(6, 8, 8, 3)
    for axis in range(3):
        sl = sampling.sample_slices(coords[..., axis], aff, poses, size, pixel)
        got = sl[:, pick][:, :, pick]                                        # rows = y, cols = x
        inside = np.all(np.abs(lab) < 59.0, axis=-1)
        assert inside.mean() > 0.2
        assert np.allclose(got[inside], lab[..., axis][inside], atol=1e-6)


def test_twin_of_a_grid_label_is_the_label_of_the_twin_pose() -> None:
    poses = _poses(10, seed=4)
    got = twin.twin_label("grid", encodings.encode("grid", poses), 1.3)
    assert np.allclose(got, encodings.encode("grid", twin.twin(poses, 1.3)))
