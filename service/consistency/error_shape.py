"""The shape of the network's pose error: how it splits over a slice's six coordinates.

A slice's tilt out of its plane and its position along its normal are far less certain than its
twist and its position in the plane: the image pins what lies in the plane, not how the plane
leans. ``svrnet-train calibrate-spread`` measures the error variance per coordinate relative to
the MC spread on the slices of simulated stacks and stores it as the model's ``mc_error_shape``
(the shipped model's values are in docs/consistency.md). The stage
(:mod:`service.consistency.motion_model`) weighs each coordinate by its own variance, so it
follows the motion closely where the network is precise and smooths where it is not.

The coordinates are those of :func:`error_coordinates`: a slice's frame turned about its normal
so that x points along the brain's left-right axis (:func:`anatomical_axes`), because the
brain's anatomy, not the scanner, makes the two tilts differ (a tilt about left-right, the head
nodding, is the harder one: the mid-sagittal symmetry pins the other).

Example (a plane whose x axis points front-back while left-right lies in its plane as y):
    >>> import numpy as np
    >>> plane = np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])         # columns: x, y, normal (atlas)
    >>> (plane @ anatomical_axes(plane)).round(6)[:, 0].tolist()        # x now along left-right
    [1.0, 0.0, 0.0]
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.geometry import se3
from service.geometry.anchors import ANCHOR_HALF_SIZE_MM

MIN_IN_PLANE = 0.5
"""A plane in which the left-right axis has a shorter projection than this (within 30 deg of
sagittal) is turned to the front-back axis instead."""


def anatomical_axes(plane_axes: ArrayLike) -> NDArray[np.float64]:
    """``[..., 3, 3]`` rotations about the normal taking a plane's axes to anatomical ones.

    ``plane_axes [..., 3, 3]``: columns x, y, normal of planes in atlas coordinates. The returned
    ``R`` keeps the normal; ``plane_axes @ R`` has its x along the projection of the atlas
    left-right axis on the plane, or of the front-back axis where the plane is near sagittal.
    """
    a = np.asarray(plane_axes, dtype=np.float64)
    lr, ap = a[..., 0, :2], a[..., 1, :2]                      # atlas x and y in the plane's (x, y)
    d = np.where(near_sagittal(a)[..., None], ap, lr)
    phi = np.arctan2(d[..., 1], d[..., 0])
    c, s = np.cos(phi), np.sin(phi)
    out = np.zeros(a.shape)
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1], out[..., 2, 2] = c, -s, s, c, 1.0
    return out


def near_sagittal(plane_axes: ArrayLike) -> NDArray[np.bool_]:
    """``[...]`` planes (columns x, y, normal in atlas coordinates) within 30 deg of sagittal: the
    atlas left-right axis projects on them shorter than :data:`MIN_IN_PLANE`.

    Example:
        >>> near_sagittal(np.stack([np.eye(3), np.eye(3)[:, [1, 2, 0]]])).tolist()   # axial, sagittal
        [False, True]
    """
    return np.linalg.norm(np.asarray(plane_axes, dtype=np.float64)[..., 0, :2], axis=-1) < MIN_IN_PLANE


def error_coordinates(pred: ArrayLike, true: ArrayLike) -> NDArray[np.float64]:
    """``[n, 6]`` the error ``E = true^-1 pred`` of poses ``[n, 4, 4]`` (plane frame -> atlas) in
    the anatomical axes of ``true``: rotation vector (mm at the anchor radius), translation (mm)."""
    t = np.asarray(true, dtype=np.float64)
    err = se3.inverse(t) @ np.asarray(pred, dtype=np.float64)
    r = anatomical_axes(t[:, :3, :3])
    rot = np.einsum("nji,nj->ni", r, se3.so3_log(err[:, :3, :3])) * ANCHOR_HALF_SIZE_MM
    return np.concatenate([rot, np.einsum("nji,nj->ni", r, err[:, :3, 3])], axis=1)


MIN_SHAPE_SHARE = 1e-3
"""The least a coordinate's variance may be of the six's mean (:func:`error_shape`): a share of 0
(a short calibration, or a network whose answers hardly vary along one coordinate) would have the
stack stage trust that coordinate without bound, and a model's metadata holds positive shares only."""


def error_shape(coordinates: ArrayLike, expected_error_mm: ArrayLike) -> NDArray[np.float64]:
    """``[6]`` variance per coordinate of errors ``[n, 6]`` in units of their expected errors, mean 1,
    none under :data:`MIN_SHAPE_SHARE` of it.

    Robust (``1.4826 x`` the median absolute value, squared): a slice the network cannot place is an
    outlier the stage rejects, not part of the noise it weighs.

    Example (errors ten times larger along the normal than in the plane):
        >>> rng = np.random.default_rng(0)
        >>> shape = error_shape(rng.normal(0, [1, 1, 1, 0.5, 0.5, 5.0], (4000, 6)), np.ones(4000))
        >>> round(float(shape[5] / shape[3]), -1)
        100.0
        >>> float(error_shape(rng.normal(0, [1, 1, 1, 1, 1, 1e-6], (400, 6)), np.ones(400))[5]) > 0.0009
        True
    """
    u = np.asarray(coordinates, dtype=np.float64) / np.asarray(expected_error_mm, dtype=np.float64)[:, None]
    var = (se3.MAD_SCALE * np.median(np.abs(u), axis=0)) ** 2
    var = np.maximum(var / var.mean(), MIN_SHAPE_SHARE)
    return var / var.mean()


DEPTH_BANDS = ((0.0, 0.35), (0.35, 0.7), (0.7, 1.0 + 1e-9))
"""Bands of relative depth in a stack over which :func:`depth_gain` is measured."""


def relative_depth(offsets_mm: ArrayLike, inside: ArrayLike) -> NDArray[np.float64]:
    """``[n]`` each slice's distance from the middle of the ``inside`` slices along the normal, in
    units of their half-extent (0 the middle, 1 the outermost slice in the brain; clipped at 1).

    Example (five slices 3 mm apart, the outer two outside the brain):
        >>> relative_depth([-6.0, -3.0, 0.0, 3.0, 6.0], [False, True, True, True, False]).tolist()
        [1.0, 1.0, 0.0, 1.0, 1.0]
    """
    z = np.asarray(offsets_mm, dtype=np.float64)
    inside = np.asarray(inside, bool)
    if inside.sum() < 2:
        return np.zeros(len(z))
    lo, hi = z[inside].min(), z[inside].max()
    return np.minimum(np.abs(z - (lo + hi) / 2.0) / max((hi - lo) / 2.0, 1e-9), 1.0)


def depth_gain(coordinates: ArrayLike, expected_error_mm: ArrayLike, depth: ArrayLike,
               gains: ArrayLike = np.linspace(0.0, 10.0, 101)) -> float:
    """``beta`` of the variance factor ``1 + beta rho^2`` by which errors ``[n, 6]`` outgrow their
    expected errors towards a stack's outer slices (``depth`` rho, :func:`relative_depth`).

    MC dropout saturates on the outer planes, where the network is lost: there its spread grows
    less than its error (the shipped model's gain is in docs/consistency.md). Measured per
    :data:`DEPTH_BANDS` (robust variance summed over the coordinates, relative to the central band),
    fitted in logs.

    Example (errors whose variance grows as 1 + 3 rho^2):
        >>> rng = np.random.default_rng(0)
        >>> rho = rng.uniform(0, 1, 20000)
        >>> err = rng.normal(0, 1, (20000, 6)) * np.sqrt(1 + 3 * rho ** 2)[:, None]
        >>> round(depth_gain(err, np.ones(20000), rho))
        3
    """
    u = np.asarray(coordinates, dtype=np.float64) / np.asarray(expected_error_mm, dtype=np.float64)[:, None]
    rho = np.asarray(depth, dtype=np.float64)
    var, mid = [], []
    for lo, hi in DEPTH_BANDS:
        m = (rho >= lo) & (rho < hi)
        var.append(((se3.MAD_SCALE * np.median(np.abs(u[m]), axis=0)) ** 2).sum())
        mid.append(np.mean(rho[m] ** 2))
    g = np.asarray(gains, dtype=np.float64)[:, None]
    model = np.log1p(g * np.asarray(mid)) - np.log1p(g * mid[0])
    return float(g[np.argmin(((model - np.log(np.asarray(var) / var[0])) ** 2).sum(1)), 0])
