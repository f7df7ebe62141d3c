"""The motion model's coupled blocks: the lever arm against composed errors, the likelihood and the
leave-one-out prediction against dense, brute-force Gaussians."""

from __future__ import annotations

import numpy as np
from scipy.stats import multivariate_normal

from service.consistency.motion_blocks import decompose, nll, to_slices
from service.consistency.motion_model import NO_VOTE, Grid, fit_motion, to_coordinates
from service.geometry import se3
from service.geometry.anchors import ANCHOR_HALF_SIZE_MM
from service.geometry.iterators import random_rotations
from service.geometry.pose import make_pose


def test_the_lever_operator_gives_back_the_slices_own_errors() -> None:
    """Slice-frame errors composed into the stack's coordinates about its centre exactly as the stage
    does (``to_coordinates``, then along the stack's axes): seen through the lever arm of each slice's
    offset along the normal they are the slice's own errors again (to second order in the error)."""
    rng = np.random.default_rng(3)
    axes = random_rotations(1, rng)[0]                                      # the stack's x, y, normal (scanner)
    centre = np.array([5.0, -10.0, 20.0])
    s = se3.exp(np.array([0.2, -0.1, 0.3, 10.0, 5.0, -3.0]))               # atlas_from_scanner (rigid, no motion)
    for z in (0.0, 30.0, -55.0, 45.0):
        slice_pose = make_pose(axes, centre + axes @ np.array([0.0, 0.0, z]))   # slice frame -> scanner
        xi = rng.normal(0, 1.0, (200, 6)) * np.sqrt([3.0, 1.0, 0.3, 0.05, 0.15, 1.5])
        err = make_pose(se3.so3_exp(xi[:, :3] / ANCHOR_HALF_SIZE_MM), xi[:, 3:])
        y = to_coordinates(s @ slice_pose @ err @ se3.inverse(slice_pose), s, centre)
        y = np.concatenate([y[:, :3] @ axes, y[:, 3:] @ axes], axis=1)     # along the stack's axes
        seen = to_slices(y, np.full(len(y), z / ANCHOR_HALF_SIZE_MM))
        np.testing.assert_allclose(seen, xi, atol=0.2, err_msg=f"z = {z}")
        if z:                                                               # uncoupled, the tilt leaks into the shift
            assert np.abs(y - xi).max() > 1.0


def _dense_covariance(z: np.ndarray, sig: np.ndarray, shape: np.ndarray, k: np.ndarray, amp2: float,
                      g2: float) -> np.ndarray:
    """``[6 m, 6 m]`` covariance of the stack-frame coordinates (coordinate-major), built directly:
    motion ``amp2 K`` per coordinate plus the slice-frame errors mapped by ``t_centre = t - s z r``."""
    m = len(z)
    a = np.eye(6 * m)                                                       # stack <- slice coordinates
    for (rot, tra), sign in (((0, 4), -1.0), ((1, 3), 1.0)):
        a[tra * m:(tra + 1) * m, rot * m:(rot + 1) * m] = -sign * np.diag(z)
    e = np.zeros((6 * m, 6 * m))
    for d in range(6):
        e[d * m:(d + 1) * m, d * m:(d + 1) * m] = np.diag(sig ** 2 * shape[:, d] / 3.0)
    return amp2 * np.kron(np.eye(6), k) + g2 * a @ e @ a.T


def test_the_blocks_likelihood_is_the_dense_gaussians() -> None:
    rng = np.random.default_rng(5)
    m = 9
    t = np.arange(m, dtype=float)
    k = np.exp(-0.5 * ((t[:, None] - t[None]) / 2.0) ** 2)
    z, sig = rng.uniform(-1, 1, m), rng.uniform(3, 9, m)
    shape = rng.uniform(0.1, 3.0, (m, 6))
    y = rng.normal(0, 5, (m, 6))
    blocks = decompose(y, sig, shape, z, k[None], (0.0,), 1.5)
    amps, scales = np.array([4.0, 36.0]), np.array([1.0, 2.25])
    got = nll(blocks, amps, scales)[0, 0]                                   # [a, g]
    for i, a2 in enumerate(amps):
        for j, g2 in enumerate(scales):
            cov = _dense_covariance(z, sig, shape, k, a2, g2) + 1e-6 * g2 * np.eye(6 * m)
            want = -multivariate_normal(np.zeros(6 * m), cov).logpdf(y.T.reshape(-1)) - 3 * m * np.log(2 * np.pi)
            np.testing.assert_allclose(got[i, j], want, rtol=1e-4)


def test_a_memo_reuses_the_factorisation_for_other_observations_only() -> None:
    """With a memo, a second call with the same errors, offsets and correlations reuses the
    eigendecompositions and gives what a fresh call gives for its own observations; other errors
    factorise anew."""
    rng = np.random.default_rng(6)
    m = 8
    t = np.arange(m, dtype=float)
    k = np.stack([np.exp(-0.5 * ((t[:, None] - t[None]) / length) ** 2) for length in (1.0, 3.0)])
    z, sig, shape = rng.uniform(-1, 1, m), rng.uniform(3, 9, m), rng.uniform(0.1, 3.0, (m, 6))
    y1, y2 = rng.normal(0, 5, (m, 6)), rng.normal(0, 5, (m, 6))
    memo: dict = {}
    first = decompose(y1, sig, shape, z, k, (0.0, 0.5), 1.5, memo)
    again = decompose(y2, sig, shape, z, k, (0.0, 0.5), 1.5, memo)
    fresh = decompose(y2, sig, shape, z, k, (0.0, 0.5), 1.5)
    assert len(memo) == 1 and all(a.u is f.u for a, f in zip(again, first))
    for a, f in zip(again, fresh):
        np.testing.assert_allclose(a.yt, f.yt, atol=1e-9)
        np.testing.assert_allclose(a.y, f.y)
    np.testing.assert_allclose(nll(again, np.array([4.0]), np.array([1.0])), nll(fresh, np.array([4.0]), np.array([1.0])))
    decompose(y2, sig * 1.5, shape, z, k, (0.0, 0.5), 1.5, memo)
    assert len(memo) == 2


def test_leave_one_out_is_the_fit_without_the_slice() -> None:
    """With independent errors, what the others predict for a slice (``loo``) is the pose a fit in
    which it does not vote gives it: the closed form over a coupled block equals refitting."""
    rng = np.random.default_rng(9)
    n, centre = 15, np.array([3.0, -4.0, 8.0])
    s = se3.exp(np.array([0.1, -0.2, 0.3, 5.0, -2.0, 7.0]))
    proposals = s @ se3.exp(rng.normal(0, [0.05] * 3 + [3.0] * 3, (n, 6)))
    sd, lever = rng.uniform(3, 9, n), np.linspace(-40, 40, n)
    shape = rng.uniform(0.1, 3.0, (n, 6))
    grid = Grid((4.0,), (6.0,), (1.0,), (0.0,))
    times = {"sequential": np.arange(n)}
    full = fit_motion(proposals, s, sd, times, centre, grid, noise_shape=shape, lever_mm=lever)
    for j in (0, 7, 14):
        votes = sd.copy()
        votes[j] = NO_VOTE
        without = fit_motion(proposals, s, votes, times, centre, grid, noise_shape=shape, lever_mm=lever)
        np.testing.assert_allclose(full.loo[j], without.poses[j], atol=1e-8)
