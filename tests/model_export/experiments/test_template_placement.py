"""The template placement's registration recovers a rigid move it is given."""

from __future__ import annotations

import numpy as np
import pytest

from service.geometry import se3
from service.geometry.pose import apply, make_pose
from service.io.volume import Volume
from tests.support.phantoms import phantom_brain

pytest.importorskip("SimpleITK")


def test_a_brain_moved_by_a_known_rigid_transform_needs_that_correction() -> None:
    from model_export.experiments.template_placement import register

    image, mask, affine = phantom_brain(3)
    centre = apply(affine, np.argwhere(mask).mean(axis=0))
    rotation = se3.so3_exp(np.radians([4.0, -3.0, 2.0]))
    shift = np.array([2.0, -1.5, 1.0])
    about_centre = make_pose(np.eye(3), centre) @ make_pose(rotation, shift) @ make_pose(np.eye(3), -centre)
    moved = Volume(image.astype(np.float32), about_centre @ affine)        # the same voxels, placed elsewhere
    ncc, degrees, mm = register(moved, Volume(image.astype(np.float32), affine), mask > 0)
    assert ncc > 0.95
    assert degrees == pytest.approx(np.degrees(np.linalg.norm(se3.so3_log(rotation))), abs=0.5)
    assert mm == pytest.approx(np.linalg.norm(shift), abs=0.5)
    ncc, degrees, mm = register(Volume(image.astype(np.float32), affine), Volume(image.astype(np.float32), affine), mask > 0)
    assert degrees < 0.3 and mm < 0.3
