"""The ITK conversion of an affine: what ITK cannot store is refused by name."""

from __future__ import annotations

import numpy as np
import pytest

from service.geometry import frames


def test_an_affine_with_an_axis_of_no_length_is_refused_as_itk_cannot_store_it() -> None:
    with pytest.raises(ValueError, match="shear"):
        frames.itk_from_affine(np.diag([1.0, 0.0, 2.0, 1.0]))


def test_axes_near_right_angles_are_stored_as_a_rotation_and_reflections_kept() -> None:
    a = np.diag([-0.8, 0.8, 3.0, 1.0])
    a[0, 1] = 0.8 * 5e-4                                      # 0.03 deg off right angles: within a file's tolerance
    _, spacing, direction = frames.itk_from_affine(a)
    np.testing.assert_allclose(direction.T @ direction, np.eye(3), atol=1e-12)
    assert np.linalg.det(direction) < 0 and np.allclose(spacing, [0.8, 0.8, 3.0], atol=1e-6)   # a reflection stays one
    with pytest.raises(ValueError, match="shear"):
        frames.itk_from_affine(np.array([[1.0, 0.01, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]))
