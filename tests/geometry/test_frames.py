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


@pytest.mark.parametrize("degrees", [45.0, 30.0, -45.0])
def test_a_slice_s_picture_is_the_same_for_every_storage_also_at_45_degrees(degrees: float) -> None:
    """A grid turned in its plane so that both in-plane voxel axes lie equally near the first world
    axis (45 degrees) is laid out by the second: its eight storages give one picture, as at 30."""
    from service.io.volume import Volume
    from service.preprocess.stack import pictures
    from model_export.experiments.localiser_sweep import STORAGES, stored_as

    c, s = (np.sqrt(0.5), np.copysign(np.sqrt(0.5), degrees)) if abs(degrees) == 45 else \
        (np.cos(np.radians(degrees)), np.sin(np.radians(degrees)))      # at 45 degrees exactly as a header writes it
    affine = np.eye(4)
    affine[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.diag([1.0, 1.2, 3.0])
    vol = Volume(np.random.default_rng(0).random((7, 5, 3)).astype(np.float32), affine)
    seen = [pictures(v.array, 2, frames.in_plane_layout(v.affine, 2)) for v in (stored_as(vol, *s) for s in STORAGES)]
    assert all(np.array_equal(s, seen[0]) for s in seen[1:])
