"""Rigid transforms applied to points: one transform or a batch, broadcast like numpy."""

from __future__ import annotations

import numpy as np
import pytest

from service.geometry import se3
from service.geometry.pose import apply


def _loop(m: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The ground truth: every broadcast pair of transform and point, one at a time."""
    shape = np.broadcast_shapes(m.shape[:-2], p.shape[:-1])
    mb, pb = np.broadcast_to(m, shape + (4, 4)), np.broadcast_to(p, shape + (3,))
    out = np.empty(shape + (3,))
    for idx in np.ndindex(shape):
        out[idx] = mb[idx][:3, :3] @ pb[idx] + mb[idx][:3, 3]
    return out


@pytest.mark.parametrize("m_shape, p_shape", [((), (3,)), ((), (7, 3)), ((), (2, 5, 3)), ((4,), (3,)),
                                              ((4,), (4, 3)), ((4, 1, 1), (1, 6, 5, 3)), ((3, 1), (3, 7, 3))])
def test_apply_maps_every_point_by_its_broadcast_transform(m_shape: tuple, p_shape: tuple) -> None:
    rng = np.random.default_rng(0)
    m = se3.exp(rng.normal(size=m_shape + (6,)) * 2.0)
    p = rng.normal(size=p_shape) * 30.0
    got = apply(m, p)
    want = _loop(m, p)
    assert got.shape == want.shape and np.abs(got - want).max() < 1e-9
