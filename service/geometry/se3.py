"""SE(3): closed-form exp/log, composition, and the statistics of MC-dropout pose samples.

Definitions follow ``shared/design/se3-notes.md`` (the paper's reference implementation, geomstats'
``SpecialEuclidean(3)`` with the left canonical metric):

* distance: ``d^2(m, x) = 2 ||log_SO3(R_m^T R)||^2 + ||t - t_m||^2`` (rad^2 and mm^2);
* Fréchet mean: Karcher mean of the rotations (Gauss-Newton ``R <- R exp(mean_i log(R^T R_i))``)
  and the arithmetic mean of the translations;
* geodesic variance: ``mean_i d^2(m, x_i)``.

All functions are batched over leading axes; poses are ``[..., 4, 4]`` float64 matrices. The
rotation part of the Fréchet mean iterates on unit quaternions, which is exact (the same
group) and several times faster than going through matrices.

Example:
    >>> import numpy as np
    >>> xi = np.array([[0.1, -0.2, 0.3, 5.0, 6.0, -7.0]])
    >>> bool(np.allclose(log(exp(xi)), xi))
    True
    >>> rot = so3_exp(np.array([[0.0, 0, 0.1], [0.0, 0, -0.1]]))
    >>> samples = make_pose(rot, np.array([[1.0, 0, 0], [-1.0, 0, 0]]))
    >>> m, v = frechet_mean_and_variance(samples)
    >>> bool(np.allclose(m, np.eye(4))), round(float(v), 6)   # 2*0.1^2 + 1^2
    (True, 1.02)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from service.geometry.pose import make_pose

ROTATION_METRIC_WEIGHT = 2.0
"""Weight of ``||omega||^2`` in the squared distance: Frobenius norm of the skew matrix."""


def hat(w: NDArray) -> NDArray:
    """Cross-product matrices ``[..., 3, 3]`` of vectors ``[..., 3]``: ``hat(w) @ u = w x u``."""
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def so3_exp(rotvec: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrices ``[..., 3, 3]`` from rotation vectors ``[..., 3]`` (radians)."""
    w = np.asarray(rotvec, dtype=np.float64)
    return Rotation.from_rotvec(w.reshape(-1, 3)).as_matrix().reshape(w.shape[:-1] + (3, 3))


def so3_log(rotation: ArrayLike) -> NDArray[np.float64]:
    """Rotation vectors ``[..., 3]`` (radians, angle in [0, pi]) of rotation matrices ``[..., 3, 3]``."""
    r = np.asarray(rotation, dtype=np.float64)
    return Rotation.from_matrix(r.reshape(-1, 3, 3)).as_rotvec().reshape(r.shape[:-2] + (3,))


def _v_coefficients(theta: NDArray) -> tuple[NDArray, NDArray]:
    """``a = (1 - cos t)/t^2`` and ``b = (t - sin t)/t^3`` with their series near 0 (``1 - cos t`` as
    ``2 sin^2(t/2)``, which keeps its digits where ``cos t`` is nearly 1)."""
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24.0, 2.0 * np.sin(t / 2.0) ** 2 / t**2)
    b = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (t - np.sin(t)) / t**3)
    return a, b


def exp(twist: ArrayLike) -> NDArray[np.float64]:
    """Group exponential: twists ``[..., 6]`` = (rotation vector, v) -> poses ``[..., 4, 4]``."""
    xi = np.asarray(twist, dtype=np.float64)
    w, v = xi[..., :3], xi[..., 3:]
    theta = np.linalg.norm(w, axis=-1)
    a, b = _v_coefficients(theta)
    k = hat(w)
    vmat = np.eye(3) + a[..., None, None] * k + b[..., None, None] * (k @ k)
    return make_pose(so3_exp(w), np.einsum("...ij,...j->...i", vmat, v))


def log(pose: ArrayLike) -> NDArray[np.float64]:
    """Group logarithm: poses ``[..., 4, 4]`` -> twists ``[..., 6]`` (inverse of :func:`exp`)."""
    m = np.asarray(pose, dtype=np.float64)
    w = so3_log(m[..., :3, :3])
    theta = np.linalg.norm(w, axis=-1)
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    # (1 - t sin t / (2 (1 - cos t))) / t^2 with 1 - cos t = 2 sin^2(t/2): written with cos t, at
    # t ~ 2e-4 its cancellation put 1e-7 mm of error on a 42 mm translation.
    c = np.where(small, 1.0 / 12.0 + theta**2 / 720.0, (1.0 - (t / 2.0) / np.tan(t / 2.0)) / t**2)
    k = hat(w)
    vinv = np.eye(3) - 0.5 * k + c[..., None, None] * (k @ k)
    return np.concatenate([w, np.einsum("...ij,...j->...i", vinv, m[..., :3, 3])], axis=-1)


def compose(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """``a o b`` (apply ``b`` first), batched with broadcasting."""
    return np.asarray(a, dtype=np.float64) @ np.asarray(b, dtype=np.float64)


def inverse(pose: ArrayLike) -> NDArray[np.float64]:
    """Inverse rigid transforms ``[..., 4, 4]`` (closed form, no matrix inversion)."""
    m = np.asarray(pose, dtype=np.float64)
    rt = np.swapaxes(m[..., :3, :3], -1, -2)
    return make_pose(rt, -np.einsum("...ij,...j->...i", rt, m[..., :3, 3]))


def squared_distance(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """Squared left-invariant geodesic distance ``2 ||log(R_a^T R_b)||^2 + ||t_b - t_a||^2``."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    rel = np.swapaxes(a[..., :3, :3], -1, -2) @ b[..., :3, :3]
    w = so3_log(rel)
    dt = b[..., :3, 3] - a[..., :3, 3]
    return ROTATION_METRIC_WEIGHT * np.sum(w * w, axis=-1) + np.sum(dt * dt, axis=-1)


def geodesic_distance(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """Geodesic distance (the paper's G.D.) between poses, batched."""
    return np.sqrt(squared_distance(a, b))


# ---- quaternion helpers (scalar-last, as scipy) -------------------------------------------------

def _cross(a: NDArray, b: NDArray) -> NDArray:
    """``a x b`` over the last axis (np.cross's axis handling dominates on small batches)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _qmul(p: NDArray, q: NDArray) -> NDArray:
    pv, pw = p[..., :3], p[..., 3:]
    qv, qw = q[..., :3], q[..., 3:]
    v = pw * qv + qw * pv + _cross(pv, qv)
    w = pw * qw - np.sum(pv * qv, axis=-1, keepdims=True)
    return np.concatenate([v, w], axis=-1)


def _qconj(q: NDArray) -> NDArray:
    return np.concatenate([-q[..., :3], q[..., 3:]], axis=-1)


def _qlog(q: NDArray) -> NDArray:
    """Rotation vectors of unit quaternions (shortest arc: sign chosen so that w >= 0)."""
    q = np.where(q[..., 3:] < 0, -q, q)
    vn = np.linalg.norm(q[..., :3], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(vn, q[..., 3:])
    scale = np.where(vn > 1e-12, angle / np.maximum(vn, 1e-300), 2.0)
    return q[..., :3] * scale


def _qexp(w: NDArray) -> NDArray:
    theta = np.linalg.norm(w, axis=-1, keepdims=True)
    half = 0.5 * theta
    s = np.where(theta > 1e-12, np.sin(half) / np.maximum(theta, 1e-300), 0.5)
    return np.concatenate([w * s, np.cos(half)], axis=-1)


def _to_quat(rotation: NDArray) -> NDArray:
    return Rotation.from_matrix(rotation.reshape(-1, 3, 3)).as_quat().reshape(rotation.shape[:-2] + (4,))


def frechet_mean_and_variance(
    poses: ArrayLike, weights: ArrayLike | None = None, *, tol: float = 1e-10, max_iter: int = 100
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Fréchet mean and geodesic variance of pose samples, optionally weighted.

    Args:
        poses: ``[..., n_samples, 4, 4]`` (e.g. ``[n_slices, n_mc, 4, 4]``).
        weights: ``[..., n_samples]`` non-negative weights (default: all equal); each batch needs a
            positive total. The weighted mean minimises ``sum_i w_i d^2(m, x_i)``.
        tol: Stop when every batch's Gauss-Newton update is below ``tol`` radians.
        max_iter: Upper bound on iterations (a handful suffice for MC-dropout clouds).

    Returns:
        ``(mean [..., 4, 4], variance [...])`` with variance ``sum_i w_i d^2(m, x_i) / sum_i w_i``.

    Example:
        >>> import numpy as np
        >>> x = make_pose(np.broadcast_to(np.eye(3), (2, 3, 3)), np.array([[0.0, 0, 0], [4.0, 0, 0]]))
        >>> m, v = frechet_mean_and_variance(x, np.array([3.0, 1.0]))
        >>> m[:3, 3].tolist(), float(v)
        ([1.0, 0.0, 0.0], 3.0)
    """
    x = np.asarray(poses, dtype=np.float64)
    if weights is None:
        w = np.full(x.shape[:-2], 1.0 / x.shape[-3])
    else:
        w = np.broadcast_to(np.asarray(weights, dtype=np.float64), x.shape[:-2])
        w = w / w.sum(axis=-1, keepdims=True)
    q = _to_quat(x[..., :3, :3])                             # [..., N, 4]
    # Start from the chordal (Markley) mean: the dominant eigenvector of sum w q q^T.
    scatter = np.einsum("...n,...ni,...nj->...ij", w, q, q)
    qm = np.linalg.eigh(scatter)[1][..., :, -1]              # [..., 4]
    # Gauss-Newton on the batch elements still moving: each stops at its own convergence.
    flat_q, flat_w = q.reshape(-1, *q.shape[-2:]), w.reshape(-1, w.shape[-1])
    flat_m = qm.reshape(-1, 4).copy()
    active = np.arange(len(flat_m))
    for _ in range(max_iter):
        if not len(active):
            break
        tangent = _qlog(_qmul(_qconj(flat_m[active])[:, None, :], flat_q[active]))    # [A, N, 3]
        step = np.einsum("an,ani->ai", flat_w[active], tangent)
        moved = _qmul(flat_m[active], _qexp(step))
        flat_m[active] = moved / np.linalg.norm(moved, axis=-1, keepdims=True)
        active = active[np.linalg.norm(step, axis=-1) >= tol]
    qm = flat_m.reshape(qm.shape)
    tangent = _qlog(_qmul(_qconj(qm)[..., None, :], q))
    t = x[..., :3, 3]
    tm = np.einsum("...n,...ni->...i", w, t)
    dt = t - tm[..., None, :]
    var = np.sum(w * (ROTATION_METRIC_WEIGHT * np.sum(tangent**2, -1) + np.sum(dt**2, -1)), axis=-1)
    rot = Rotation.from_quat(qm.reshape(-1, 4)).as_matrix().reshape(qm.shape[:-1] + (3, 3))
    return make_pose(rot, tm), var


def frechet_mean(poses: ArrayLike, weights: ArrayLike | None = None, **kwargs: float) -> NDArray[np.float64]:
    """Fréchet mean ``[..., 4, 4]`` of ``[..., n_samples, 4, 4]``; see :func:`frechet_mean_and_variance`."""
    return frechet_mean_and_variance(poses, weights, **kwargs)[0]


def geodesic_variance(poses: ArrayLike, mean: ArrayLike | None = None) -> NDArray[np.float64]:
    """``mean_i d^2(m, x_i)`` about ``mean`` (default: the Fréchet mean)."""
    x = np.asarray(poses, dtype=np.float64)
    if mean is None:
        return frechet_mean_and_variance(x)[1]
    return squared_distance(np.asarray(mean)[..., None, :, :], x).mean(axis=-1)


MAD_SCALE = 1.4826
"""Makes the MAD a consistent estimator of the standard deviation for normal data (the paper's K)."""


TUKEY_C = 4.685
"""Tukey's biweight constant: 95 % efficiency for normal residuals."""


def tukey_weights(residuals: ArrayLike, scale: float) -> NDArray[np.float64]:
    """Tukey's biweight of non-negative ``residuals`` at robust ``scale``: ``(1 - u^2)^2`` for
    ``u = r / (TUKEY_C scale) < 1``, else 0.

    Example:
        >>> tukey_weights([0.0, 4.685, 10.0], 2.0).round(3).tolist()
        [1.0, 0.562, 0.0]
    """
    u = np.asarray(residuals, dtype=np.float64) / (TUKEY_C * scale)
    return np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0)


def mad_outliers(values: ArrayLike, k: float = 3.0, axis: int = -1) -> NDArray[np.bool_]:
    """The paper's rule: ``|x - median| > k * MAD`` with ``MAD = 1.4826 median(|x - median|)``.

    Example:
        >>> mad_outliers([1.0, 1.1, 0.9, 1.0, 9.0]).tolist()
        [False, False, False, False, True]
    """
    x = np.asarray(values, dtype=np.float64)
    med = np.median(x, axis=axis, keepdims=True)
    mad = MAD_SCALE * np.median(np.abs(x - med), axis=axis, keepdims=True)
    return np.abs(x - med) > k * mad
