"""Dense grid labels: the atlas mm of ``G x G`` points of the slice plane, decoded by weighted Kabsch.

The paper's three anchor points generalised: the label of a pose ``T`` is ``T @ q`` for
every point ``q`` of a regular ``G x G`` grid spanning the same ``120 mm x 120 mm`` plane as the
anchors (``[-h, h]^2`` at ``z = 0``, ``h = ANCHOR_HALF_SIZE_MM``), flattened row by row as
``(x, y, z)`` triples: ``3 G^2`` numbers (192 for the default ``G = 8``), 21x the supervision of the
anchors per slice.

Decoding fits the rigid transform that best maps the template onto the predicted points in the
weighted least-squares sense (Kabsch / Umeyama without scale). Because the template is planar, the
fit is unique as soon as the predicted points are not collinear, and it is found in closed form
(the first two columns of the rotation are a 3 x 2 polar factor, the third their cross product:
proper, det +1, whatever the noise); collinear or non-finite predictions go through the SVD with its
sign correction and decode to some proper rotation (never NaN).

Example:
    >>> import numpy as np
    >>> from service.geometry import se3
    >>> pose = se3.exp(np.array([0.4, -1.1, 2.0, 5.0, -3.0, 12.0]))
    >>> label = encode(pose)
    >>> label.shape, bool(np.allclose(decode(label), pose))
    ((192,), True)
    >>> noisy = label + np.random.default_rng(0).normal(scale=2.0, size=label.shape)
    >>> rot = decode(noisy)[:3, :3]
    >>> bool(np.isclose(np.linalg.det(rot), 1.0)), bool(np.allclose(rot.T @ rot, np.eye(3)))
    (True, True)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.geometry.anchors import ANCHOR_HALF_SIZE_MM
from service.geometry.pose import make_pose

GRID_SIZE = 8
"""Points per side of the default grid label."""


def template(size: int = GRID_SIZE, half_mm: float = ANCHOR_HALF_SIZE_MM) -> NDArray[np.float64]:
    """Grid points ``[size^2, 3]`` in the slice frame (mm), row-major: ``y`` outer, ``x`` inner.

    Example:
        >>> template(2).tolist()
        [[-60.0, -60.0, 0.0], [60.0, -60.0, 0.0], [-60.0, 60.0, 0.0], [60.0, 60.0, 0.0]]
    """
    u = np.linspace(-half_mm, half_mm, size)
    yy, xx = np.meshgrid(u, u, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel(), np.zeros(size * size)], axis=1)


TEMPLATE = template()


def encode(pose: ArrayLike, size: int = GRID_SIZE) -> NDArray[np.float64]:
    """Poses ``[..., 4, 4]`` -> grid labels ``[..., 3 size^2]`` (atlas mm of each plane point)."""
    m = np.asarray(pose, dtype=np.float64)
    q = TEMPLATE if size == GRID_SIZE else template(size)
    pts = np.einsum("...ij,pj->...pi", m[..., :3, :3], q) + m[..., None, :3, 3]
    return pts.reshape(m.shape[:-2] + (3 * len(q),))


def kabsch(source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None) -> NDArray[np.float64]:
    """Proper rigid ``[..., 4, 4]`` minimising ``sum_i w_i |R s_i + t - p_i|^2`` (points ``[..., P, 3]``).

    ``source`` may be shared (``[P, 3]``) or batched like ``target``. Weights default to 1 and are
    clipped at 0; an all-zero weight vector falls back to uniform weights.

    Example:
        >>> import numpy as np
        >>> src = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
        >>> rot = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
        >>> fit = kabsch(src, src @ rot.T + [1.0, 2.0, 3.0])
        >>> fit.round(6).tolist()[0], fit[:3, 3].round(6).tolist()
        ([0.0, -1.0, 0.0, 1.0], [1.0, 2.0, 3.0])
    """
    p = np.asarray(target, dtype=np.float64)
    src = np.asarray(source, dtype=np.float64)
    ok = np.all(np.isfinite(p), axis=(-1, -2), keepdims=True)
    p = np.where(ok, p, src)                                  # non-finite predictions -> identity fit
    if weights is None and src.ndim == 2:
        # shared source, equal weights (the MC statistics decode B x N labels): one broadcast product
        cs, cp = src.mean(0), p.mean(-2)
        h = np.matmul(((src - cs) / len(src)).T, p)                                    # [..., 3, 3]
    else:
        s = np.broadcast_to(src, p.shape)
        w = np.ones(p.shape[:-1]) if weights is None else np.clip(np.asarray(weights, dtype=np.float64), 0.0, None)
        w = np.broadcast_to(w, p.shape[:-1])
        total = w.sum(-1, keepdims=True)
        w = np.where(total > 0, w, 1.0) / np.where(total > 0, total, w.shape[-1])
        cs = (w[..., None, :] @ s)[..., 0, :]
        cp = (w[..., None, :] @ p)[..., 0, :]
        h = np.swapaxes((s - cs[..., None, :]) * w[..., None], -1, -2) @ (p - cp[..., None, :])   # [..., 3, 3]
    if src.ndim == 2 and not src[:, 2].any():                  # a planar source: closed form
        rot, fitted = _planar_rotation(np.swapaxes(h[..., :2, :], -1, -2))
    else:
        rot, fitted = np.zeros(h.shape), np.zeros(h.shape[:-2], bool)
    if not fitted.all():
        rot[~fitted] = _svd_rotation(h[~fitted])
    return make_pose(rot, cp - (rot @ cs[..., None])[..., 0])


def _svd_rotation(h: NDArray[np.float64]) -> NDArray[np.float64]:
    """The proper rotation ``R`` maximising ``tr(R h)`` for cross-covariances ``h [..., 3, 3]`` (SVD)."""
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(u @ vt))
    d = np.where(d == 0, 1.0, d)
    fix = np.broadcast_to(np.eye(3), h.shape).copy()
    fix[..., 2, 2] = d
    return np.swapaxes(vt, -1, -2) @ fix @ np.swapaxes(u, -1, -2)   # V diag(1, 1, d) U^T


def _planar_rotation(b: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Kabsch for a source in the plane ``z = 0``, in closed form: only the rotation's first two
    columns act on it, and the best ones are the orthonormal polar factor ``b (b^T b)^(-1/2)`` of
    ``b [..., 3, 2]`` (the cross-covariance's first two rows, transposed); the third is their cross
    product (a proper rotation, as the SVD's sign correction gives). ``b^T b`` is 2 x 2, so its
    inverse square root is explicit: no batched SVD. Returns the rotations and where ``b`` has full
    rank (elsewhere: collinear points; the caller falls back to the SVD)."""
    c = np.swapaxes(b, -1, -2) @ b                                           # [..., 2, 2], symmetric
    det = c[..., 0, 0] * c[..., 1, 1] - c[..., 0, 1] ** 2
    trace = c[..., 0, 0] + c[..., 1, 1]
    fitted = det > 1e-12 * trace ** 2
    root_det = np.sqrt(np.where(fitted, det, 1.0))
    root = (c + root_det[..., None, None] * np.eye(2)) / np.sqrt(trace + 2.0 * root_det)[..., None, None]   # sqrt(c)
    inv_root = np.stack([np.stack([root[..., 1, 1], -root[..., 0, 1]], -1),
                         np.stack([-root[..., 1, 0], root[..., 0, 0]], -1)], -2) / root_det[..., None, None]
    cols = b @ inv_root                                                      # [..., 3, 2] orthonormal columns
    rot = np.concatenate([cols, np.cross(cols[..., 0], cols[..., 1])[..., None]], axis=-1)
    return rot, fitted


def decode(label: ArrayLike, weights: ArrayLike | None = None) -> NDArray[np.float64]:
    """Grid labels ``[..., 3 G^2]`` -> poses ``[..., 4, 4]`` by a weighted Kabsch fit to the template.

    Args:
        label: predicted atlas points, flattened as by :func:`encode` (``G`` from the length).
        weights: optional ``[..., G^2]`` confidence of each point (default uniform).
    """
    lab = np.asarray(label, dtype=np.float64)
    n = lab.shape[-1] // 3
    size = int(round(np.sqrt(n)))
    if size * size * 3 != lab.shape[-1]:
        raise ValueError(f"a grid label has 3 G^2 numbers; got {lab.shape[-1]}")
    q = TEMPLATE if size == GRID_SIZE else template(size)
    return kabsch(q, lab.reshape(lab.shape[:-1] + (n, 3)), weights)
