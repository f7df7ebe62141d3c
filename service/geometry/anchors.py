"""Anchor-point labels (paper, "Loss Functions and Ground Truth Labels" and "Transformation Recovery").

Three points of the slice plane, carried by the pose: ``P1 = (-h, -h, 0)`` (bottom-left corner),
``P2 = (0, 0, 0)`` (centre) and ``P3 = (h, -h, 0)`` (bottom-right corner) with
``h = ANCHOR_HALF_SIZE_MM = 60`` mm, i.e. the corners of a 120 mm x 120 mm plane (the field of
view of the default model: 96 px of 1.25 mm). The scale is fixed, independent of any model, so
anchor-point errors (the paper's E.D.) mean the same thing for every model.

Example:
    >>> import numpy as np
    >>> pts = encode(np.eye(4))
    >>> pts.reshape(3, 3).tolist()
    [[-60.0, -60.0, 0.0], [0.0, 0.0, 0.0], [60.0, -60.0, 0.0]]
    >>> bool(np.allclose(decode(pts), np.eye(4)))
    True
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.geometry import se3
from service.geometry.pose import make_pose

ANCHOR_HALF_SIZE_MM = 60.0
TEMPLATE = np.array(
    [[-ANCHOR_HALF_SIZE_MM, -ANCHOR_HALF_SIZE_MM, 0.0],
     [0.0, 0.0, 0.0],
     [ANCHOR_HALF_SIZE_MM, -ANCHOR_HALF_SIZE_MM, 0.0]]
)
"""Anchor points in the slice frame, rows P1, P2, P3 (mm)."""

MIN_DISTANCE_FRACTION = 0.25
"""Anchors closer than this fraction of their nominal spacing (``h sqrt 2`` for P1-P2 / P2-P3,
``2h`` for P1-P3), or nearly collinear, make a degenerate prediction."""


def encode(pose: ArrayLike) -> NDArray[np.float64]:
    """Poses ``[..., 4, 4]`` -> anchor labels ``[..., 9]`` = (P1, P2, P3) in atlas mm."""
    m = np.asarray(pose, dtype=np.float64)
    pts = np.einsum("...ij,pj->...pi", m[..., :3, :3], TEMPLATE) + m[..., None, :3, 3]
    return pts.reshape(m.shape[:-2] + (9,))


def decode(points: ArrayLike) -> NDArray[np.float64]:
    """Anchor labels ``[..., 9]`` -> poses ``[..., 4, 4]`` by the paper's recovery rules.

    ``t = P2``; the x axis is ``P3 - P1``; the normal is ``(P3 - P1) x (P2 - P1)``; the y axis
    completes a right-handed frame (normal x x-axis). The result is always a proper rotation
    (orthonormal, det +1), whatever the noise; degenerate inputs are reported by
    :func:`degenerate` and decode to some proper rotation rather than NaN.
    """
    p = np.asarray(points, dtype=np.float64).reshape(np.shape(points)[:-1] + (3, 3))
    p1, p2, p3 = p[..., 0, :], p[..., 1, :], p[..., 2, :]
    v1 = p3 - p1
    v2 = p2 - p1
    x = _unit(v1, fallback=np.array([1.0, 0.0, 0.0]))
    n = _unit(np.cross(v1, v2), fallback=_any_perpendicular(x))
    n = _unit(n - np.sum(n * x, -1, keepdims=True) * x, fallback=_any_perpendicular(x))
    y = np.cross(n, x)
    return make_pose(np.stack([x, y, n], axis=-1), p2)


def ed(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """The paper's E.D.: mean distance (mm) of the three anchor points of poses ``a`` and ``b`` (broadcast).

    Example:
        >>> import numpy as np
        >>> shifted = np.eye(4); shifted[0, 3] = 3.0
        >>> float(ed(np.eye(4), shifted))
        3.0
    """
    pa = encode(a).reshape(np.shape(a)[:-2] + (3, 3))
    pb = encode(b).reshape(np.shape(b)[:-2] + (3, 3))
    return np.linalg.norm(pa - pb, axis=-1).mean(axis=-1)


def degenerate(points: ArrayLike, min_fraction: float = MIN_DISTANCE_FRACTION) -> NDArray[np.bool_]:
    """True where predicted anchors are too close together or nearly collinear.

    Example:
        >>> import numpy as np
        >>> bad = encode(np.eye(4)).reshape(3, 3); bad[2] = bad[0] + 1.0
        >>> degenerate(np.stack([encode(np.eye(4)), bad.ravel()])).tolist()
        [False, True]
    """
    p = np.asarray(points, dtype=np.float64).reshape(np.shape(points)[:-1] + (3, 3))
    d12 = np.linalg.norm(p[..., 1, :] - p[..., 0, :], axis=-1)
    d23 = np.linalg.norm(p[..., 2, :] - p[..., 1, :], axis=-1)
    d13 = np.linalg.norm(p[..., 2, :] - p[..., 0, :], axis=-1)
    h = ANCHOR_HALF_SIZE_MM
    close = (np.minimum(d12, d23) < min_fraction * h * np.sqrt(2)) | (d13 < min_fraction * 2 * h)
    # Twice the triangle area; nominal value is 2 h^2.
    area2 = np.linalg.norm(np.cross(p[..., 2, :] - p[..., 0, :], p[..., 1, :] - p[..., 0, :]), axis=-1)
    flat = area2 < min_fraction * 2 * h * h
    return close | flat | ~np.all(np.isfinite(p), axis=(-1, -2))


def _unit(v: NDArray, fallback: NDArray) -> NDArray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    fb = np.broadcast_to(fallback, v.shape)
    ok = np.isfinite(n) & (n > 1e-9)
    return np.where(ok, v / np.where(ok, n, 1.0), fb)


def _any_perpendicular(x: NDArray) -> NDArray:
    """A unit vector perpendicular to each unit ``x`` (used only for degenerate input)."""
    other = np.where(np.abs(x[..., :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    c = np.cross(x, other)
    return c / np.linalg.norm(c, axis=-1, keepdims=True)


def twist_spread_mm(cov: ArrayLike) -> NDArray[np.float64]:
    """The scale of the E.D. of an uncertain pose: the RMS displacement (mm) of the anchor points under
    a right perturbation ``P exp(d)``, ``d ~ N(0, cov)`` (``cov [..., 6, 6]``, rotation in radians, then
    translation in mm, in the pose's own frame). Anchor ``a`` moves by ``w x a + v``.

    Example (1 mm^2 of translation along each axis, no rotation: every anchor moves sqrt(3) mm):
        >>> import numpy as np
        >>> cov = np.diag([0.0, 0.0, 0.0, 1.0, 1.0, 1.0])
        >>> round(float(twist_spread_mm(cov)), 4)
        1.7321
    """
    lever = np.concatenate([-se3.hat(TEMPLATE), np.broadcast_to(np.eye(3), (len(TEMPLATE), 3, 3))], axis=2)   # [3, 3, 6]
    c = np.asarray(cov, dtype=np.float64)
    return np.sqrt(np.maximum(np.einsum("aij,...jk,aik->...", lever, c, lever) / len(TEMPLATE), 0.0))

