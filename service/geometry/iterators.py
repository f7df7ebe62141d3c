"""Pose iterators of the paper ("Generating Training and Validation Data", "Implementation").

Every iterator returns slice poses ``[N, 4, 4]`` (slice mm -> atlas mm) about a ``centre`` (atlas
mm, e.g. the brain centre): the identity plane is rotated, then shifted along its new normal by
``Tz``, i.e. ``R = rotation``, ``t = centre + R @ (0, 0, Tz)``. ``Tz`` stays within the central 70 %
of the volume: ``|Tz| <= 0.35 L`` (:func:`tz_limit`).

Example:
    >>> poses = euler_grid(tz_max_mm=4.0, tz_step_mm=2.0)
    >>> poses.shape                 # 10 angles per axis, 5 offsets
    (5000, 4, 4)
    >>> fibonacci_normals(300).shape
    (300, 3)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from service.geometry.pose import make_pose

GOLDEN_RATIO = (np.sqrt(5.0) + 1.0) / 2.0
TZ_FRACTION = 0.35


def tz_limit(length_mm: float) -> float:
    """``0.35 L``: the largest ``|Tz|`` kept (central 70 % of a volume of side ``L``)."""
    return TZ_FRACTION * float(length_mm)


def _tz_values(tz_max_mm: float, tz_step_mm: float) -> NDArray:
    n = int(np.floor(tz_max_mm / tz_step_mm + 1e-9))
    return np.arange(-n, n + 1) * tz_step_mm


def _place(rotations: NDArray, tz: NDArray, centre: ArrayLike) -> NDArray[np.float64]:
    c = np.asarray(centre, dtype=np.float64)
    t = c + rotations[..., :, 2] * tz[..., None]
    return make_pose(rotations, t)


def _grid(rotations: NDArray, tz: NDArray, centre: ArrayLike) -> NDArray[np.float64]:
    """Every rotation at every offset (rotation-major order)."""
    r = np.repeat(rotations, len(tz), axis=0)
    return _place(r, np.tile(tz, len(rotations)), centre)


def euler_grid(
    *,
    step_deg: float = 18.0,
    max_deg: float = 90.0,
    tz_max_mm: float = 40.0,
    tz_step_mm: float = 2.0,
    centre: ArrayLike = (0.0, 0.0, 0.0),
) -> NDArray[np.float64]:
    """Euler iterator: extrinsic x-y-z angles in ``[-max, max)`` by ``step`` on each axis, x Tz steps.

    With the defaults: 10 angles per axis (-90 ... 72 degrees) and Tz in 2 mm steps.
    """
    a = np.deg2rad(np.arange(-max_deg, max_deg - 1e-9, step_deg))
    ang = np.stack(np.meshgrid(a, a, a, indexing="ij"), axis=-1).reshape(-1, 3)
    return _grid(Rotation.from_euler("xyz", ang).as_matrix(), _tz_values(tz_max_mm, tz_step_mm), centre)


def fibonacci_normals(n: int) -> NDArray[np.float64]:
    """The paper's Fibonacci sphere: ``z_i = 1 - (2i+1)/n``, ``phi_i = 2 pi i / Phi``."""
    i = np.arange(n, dtype=np.float64)
    z = 1.0 - (2.0 * i + 1.0) / n
    phi = 2.0 * np.pi * i / GOLDEN_RATIO
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def rotation_to_normal(normals: ArrayLike) -> NDArray[np.float64]:
    """Smallest rotations ``[N, 3, 3]`` taking ``(0, 0, 1)`` onto each unit normal (Rodrigues)."""
    n = np.asarray(normals, dtype=np.float64)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    axis = np.cross(np.array([0.0, 0.0, 1.0]), n)
    s = np.linalg.norm(axis, axis=-1)
    angle = np.arctan2(s, n[..., 2])
    # Antipodal normal: any axis in the plane works; use x.
    axis = np.where(s[..., None] > 1e-12, axis / np.maximum(s, 1e-300)[..., None], np.array([1.0, 0, 0]))
    return Rotation.from_rotvec((axis * angle[..., None]).reshape(-1, 3)).as_matrix().reshape(n.shape[:-1] + (3, 3))


def _inplane(rot_normal: NDArray, theta: NDArray) -> NDArray:
    rz = Rotation.from_euler("z", theta.reshape(-1, 1)).as_matrix().reshape(theta.shape + (3, 3))
    return rot_normal @ rz


def fibonacci_grid(
    *,
    n_normals: int = 300,
    n_inplane: int = 10,
    inplane_range: float = np.pi,
    tz_max_mm: float = 40.0,
    tz_step_mm: float = 4.0,
    centre: ArrayLike = (0.0, 0.0, 0.0),
) -> NDArray[np.float64]:
    """Fibonacci iterator: normals x in-plane rotations over ``[0, inplane_range)`` x Tz steps."""
    rn = rotation_to_normal(fibonacci_normals(n_normals))
    theta = np.arange(n_inplane) * (inplane_range / n_inplane)
    rot = _inplane(np.repeat(rn, n_inplane, axis=0), np.tile(theta, n_normals))
    return _grid(rot, _tz_values(tz_max_mm, tz_step_mm), centre)


def random_rotations(
    n: int, rng: np.random.Generator, inplane_range: float = np.pi
) -> NDArray[np.float64]:
    """Uniform random normals x uniform in-plane angles in ``[0, inplane_range)`` (validation)."""
    v = rng.normal(size=(n, 3))
    theta = rng.uniform(0.0, inplane_range, size=n)
    return _inplane(rotation_to_normal(v), theta)


def random_poses(
    n: int,
    rng: np.random.Generator,
    *,
    tz_max_mm: float = 40.0,
    inplane_range: float = np.pi,
    centre: ArrayLike = (0.0, 0.0, 0.0),
) -> NDArray[np.float64]:
    """Random validation poses within the bounds of the training iterators (continuous motion)."""
    return _place(random_rotations(n, rng, inplane_range), rng.uniform(-tz_max_mm, tz_max_mm, n), centre)
