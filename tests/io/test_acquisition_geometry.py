"""A grid is refused past the voxel and field-of-view limits and accepted up to them, whatever its
orientation."""

from __future__ import annotations

import numpy as np
import pytest

from service.geometry import se3
from service.io.acquisition_geometry import MAX_FIELD_OF_VIEW_MM, MAX_VOXEL_MM, MIN_VOXEL_MM, grid_problem


def turned(edges: tuple[float, float, float]) -> np.ndarray:
    a = np.eye(4)
    a[:3, :3] = se3.so3_exp(np.array([0.4, -0.7, 1.1])) * np.asarray(edges)
    a[:3, 3] = [-120.0, 40.0, 300.0]
    return a


@pytest.mark.parametrize(("edges", "shape", "problem"), [
    ((MIN_VOXEL_MM, 1.0, 3.0), (10, 10, 10), None),
    ((MIN_VOXEL_MM * 0.99, 1.0, 3.0), (10, 10, 10), "under"),
    ((1.0, 1.0, MAX_VOXEL_MM), (10, 10, 10), None),
    ((1.0, 1.0, MAX_VOXEL_MM * 1.01), (10, 10, 10), "beyond 20 mm"),
    ((2.0, 1.0, 3.0), (int(MAX_FIELD_OF_VIEW_MM / 2), 10, 10), None),
    ((2.0, 1.0, 3.0), (int(MAX_FIELD_OF_VIEW_MM / 2) + 1, 10, 10), "field of view 1002 x 10 x 30 mm"),
])
def test_the_limits_hold_along_any_axis_in_any_orientation(edges: tuple, shape: tuple, problem: str | None) -> None:
    found = grid_problem(turned(edges), shape)
    assert found is None if problem is None else problem in found, found
    assert grid_problem(turned(edges)[:, [2, 0, 1, 3]], shape[2:] + shape[:2]) is None if problem is None else True


def test_a_slice_is_a_grid_one_voxel_deep() -> None:
    assert grid_problem(turned((0.5, 0.5, 4.0)), (512, 512, 1)) is None
    assert "field of view" in grid_problem(turned((2.5, 2.5, 4.0)), (512, 512, 1))
