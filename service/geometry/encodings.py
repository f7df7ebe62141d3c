"""Pose label encodings: the paper's anchor points (9), Euler-Cartesian (6), Quaternion-Cartesian (7), and a grid (192).

Each encoding is a pair of vectorised functions pose ``[..., 4, 4]`` <-> label ``[..., D]`` and a
list of named components, one per output branch of the network (the multi-loss framework).

* ``anchor``: ``P1, P2, P3`` in atlas mm (see :mod:`service.geometry.anchors`).
* ``euler``: extrinsic x-y-z Euler angles (radians), then the translation (mm).
* ``quaternion``: unit quaternion ``(w, x, y, z)`` with ``w >= 0``, then the translation (mm);
  decoding normalises the predicted quaternion (PoseNet convention).
* ``grid``: the atlas mm of an ``8 x 8`` grid of slice-plane points (see :mod:`service.geometry.grid`),
  decoded by a weighted Kabsch fit (always a proper rotation).

Example:
    >>> import numpy as np
    >>> from service.geometry import se3
    >>> pose = se3.exp(np.array([0.3, -0.2, 0.1, 4.0, 5.0, 6.0]))
    >>> all(np.allclose(decode(k, encode(k, pose)), pose) for k in LABEL_TYPES)
    True
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from service.geometry import anchors, grid
from service.geometry.pose import make_pose


def _flat_rot(pose: NDArray) -> Rotation:
    return Rotation.from_matrix(pose[..., :3, :3].reshape(-1, 3, 3))


def euler_encode(pose: ArrayLike) -> NDArray[np.float64]:
    m = np.asarray(pose, dtype=np.float64)
    ang = _flat_rot(m).as_euler("xyz").reshape(m.shape[:-2] + (3,))
    return np.concatenate([ang, m[..., :3, 3]], axis=-1)


def euler_decode(label: ArrayLike) -> NDArray[np.float64]:
    v = np.asarray(label, dtype=np.float64)
    rot = Rotation.from_euler("xyz", v[..., :3].reshape(-1, 3)).as_matrix()
    return make_pose(rot.reshape(v.shape[:-1] + (3, 3)), v[..., 3:6])


def quaternion_encode(pose: ArrayLike) -> NDArray[np.float64]:
    m = np.asarray(pose, dtype=np.float64)
    q = _flat_rot(m).as_quat(canonical=True, scalar_first=True).reshape(m.shape[:-2] + (4,))
    return np.concatenate([q, m[..., :3, 3]], axis=-1)


def quaternion_decode(label: ArrayLike) -> NDArray[np.float64]:
    v = np.asarray(label, dtype=np.float64)
    q = v[..., :4].reshape(-1, 4)
    q = np.where(np.linalg.norm(q, axis=-1, keepdims=True) > 1e-12, q, np.array([1.0, 0, 0, 0]))
    rot = Rotation.from_quat(q, scalar_first=True).as_matrix()
    return make_pose(rot.reshape(v.shape[:-1] + (3, 3)), v[..., 4:7])


@dataclass(frozen=True)
class Encoding:
    """A label type: its size, its branches (name, slice of the label) and its codec."""

    name: str
    size: int
    branches: tuple[tuple[str, slice], ...]
    encode: Callable[[ArrayLike], NDArray[np.float64]]
    decode: Callable[[ArrayLike], NDArray[np.float64]]


ENCODINGS: dict[str, Encoding] = {
    "anchor": Encoding("anchor", 9, (("p1", slice(0, 3)), ("p2", slice(3, 6)), ("p3", slice(6, 9))),
                       anchors.encode, anchors.decode),
    "euler": Encoding("euler", 6, (("rotation", slice(0, 3)), ("translation", slice(3, 6))),
                      euler_encode, euler_decode),
    "quaternion": Encoding("quaternion", 7, (("rotation", slice(0, 4)), ("translation", slice(4, 7))),
                           quaternion_encode, quaternion_decode),
    "grid": Encoding("grid", 3 * grid.GRID_SIZE**2, (("points", slice(0, 3 * grid.GRID_SIZE**2)),),
                     grid.encode, grid.decode),
}
LABEL_TYPES = tuple(ENCODINGS)


def get(label_type: str) -> Encoding:
    """The :class:`Encoding` called ``label_type`` (``anchor``, ``euler``, ``quaternion`` or ``grid``)."""
    try:
        return ENCODINGS[label_type]
    except KeyError:
        raise ValueError(f"unknown label type {label_type!r}; expected one of {LABEL_TYPES}") from None


def encode(label_type: str, pose: ArrayLike) -> NDArray[np.float64]:
    return get(label_type).encode(pose)


def decode(label_type: str, label: ArrayLike) -> NDArray[np.float64]:
    return get(label_type).decode(label)
