"""Anchor points and the Euler/Quaternion encodings: round trips, noise, degeneracy."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.geometry import anchors, encodings, se3
from service.geometry.anchors import ANCHOR_HALF_SIZE_MM


def poses_from_seed(seed: int, n: int = 64) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return se3.exp(np.concatenate([rng.normal(size=(n, 3)), rng.normal(scale=30, size=(n, 3))], -1))


def test_anchor_template_is_the_papers_corners() -> None:
    h = ANCHOR_HALF_SIZE_MM
    np.testing.assert_allclose(anchors.TEMPLATE, [[-h, -h, 0], [0, 0, 0], [h, -h, 0]])


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 100_000))
@pytest.mark.parametrize("label_type", encodings.LABEL_TYPES)
def test_encode_decode_round_trip(label_type: str, seed: int) -> None:
    p = poses_from_seed(seed)
    np.testing.assert_allclose(encodings.decode(label_type, encodings.encode(label_type, p)), p, atol=1e-9)
    assert encodings.encode(label_type, p).shape == (64, encodings.get(label_type).size)


@pytest.mark.parametrize("noise_mm", [0.5, 5.0, 30.0])
def test_noisy_anchors_decode_to_proper_rotations(noise_mm: float) -> None:
    rng = np.random.default_rng(1)
    p = poses_from_seed(2, 500)
    noisy = anchors.encode(p) + rng.normal(scale=noise_mm, size=(500, 9))
    r = anchors.decode(noisy)[:, :3, :3]
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), np.broadcast_to(np.eye(3), r.shape), atol=1e-10)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-10)
    # Translation is P2 exactly; rotation error shrinks with noise.
    np.testing.assert_allclose(anchors.decode(noisy)[:, :3, 3], noisy[:, 3:6])
    err = np.rad2deg(np.linalg.norm(se3.so3_log(np.swapaxes(p[:, :3, :3], -1, -2) @ r), axis=-1))
    assert np.median(err) < 2.0 * noise_mm  # ~ noise / 60 mm lever arm, in degrees


def test_degenerate_anchors_are_flagged() -> None:
    good = anchors.encode(poses_from_seed(3, 10))
    assert not anchors.degenerate(good).any()
    coincident = good.copy()
    coincident[:, 6:9] = coincident[:, 0:3] + 0.5
    collinear = good.copy()
    collinear[:, 3:6] = 0.5 * (good[:, 0:3] + good[:, 6:9])
    nan = good.copy()
    nan[:, 0] = np.nan
    assert anchors.degenerate(coincident).all()
    assert anchors.degenerate(collinear).all()
    assert anchors.degenerate(nan).all()
    r = anchors.decode(np.concatenate([coincident, collinear]))[:, :3, :3]
    assert np.isfinite(r).all()
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-9)


def test_quaternion_decode_normalises_and_is_wxyz() -> None:
    pose = se3.exp(np.array([0.0, 0.0, np.pi / 2, 1, 2, 3]))
    q = encodings.quaternion_encode(pose)
    np.testing.assert_allclose(q[:4], [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)], atol=1e-12)
    np.testing.assert_allclose(encodings.quaternion_decode(np.r_[3 * q[:4], q[4:]]), pose, atol=1e-12)


def test_unknown_label_type() -> None:
    with pytest.raises(ValueError, match="anchor"):
        encodings.get("matrix")


def test_the_twist_spread_is_the_rms_anchor_displacement_of_sampled_perturbations() -> None:
    """``twist_spread_mm`` against perturbations drawn from the covariance: the RMS distance each
    anchor moves under ``P exp(d)`` (small twists, where the linear lever is exact to a percent)."""
    rng = np.random.default_rng(5)
    root = rng.normal(size=(6, 6)) * np.array([0.01, 0.01, 0.01, 0.8, 0.8, 0.8])[:, None]
    cov = root @ root.T                                                    # correlated rotation and shift
    pose = se3.exp(rng.normal(size=6) * [0.5, 0.5, 0.5, 20, 20, 20])
    d = rng.multivariate_normal(np.zeros(6), cov, size=20000)
    moved = anchors.encode(pose @ se3.exp(d)).reshape(-1, 3, 3) - anchors.encode(pose).reshape(1, 3, 3)
    sampled = np.sqrt(np.mean(np.sum(moved ** 2, axis=-1)))
    assert anchors.twist_spread_mm(cov) == pytest.approx(sampled, rel=0.02)
    assert anchors.twist_spread_mm(np.stack([cov, 4 * cov])) == pytest.approx([sampled, 2 * sampled], rel=0.02)
