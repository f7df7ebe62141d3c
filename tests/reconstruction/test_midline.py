"""A reconstruction's own midline put on the atlas plane: the correction undoes a move that a mirror
sees, leaves alone one it cannot see, and is not applied where it would be implausibly large."""

from __future__ import annotations

import numpy as np
import pytest

from service.geometry import se3
from service.geometry.pose import make_pose, translate
from service.io.volume import Volume
from service.reconstruction import midline, quality
from service.reconstruction.midline import MAX_ROTATION_DEG, midline_fit
from tests.support.phantoms import symmetric_phantom_brain


def moved(rot_deg: list[float], shift_mm: list[float]) -> tuple[Volume, np.ndarray]:
    """The symmetric phantom moved in the world by a rigid ``G`` about its centre; returns it and ``G``."""
    image, mask, affine = symmetric_phantom_brain(3)
    centre = np.argwhere(mask > 0.5).mean(axis=0) @ affine[:3, :3].T + affine[:3, 3]
    g = translate(centre) @ make_pose(se3.so3_exp(np.radians(rot_deg)), shift_mm) @ se3.inverse(translate(centre))
    return Volume(image, g @ affine), g


def size(t: np.ndarray) -> tuple[float, float]:
    return float(np.degrees(np.linalg.norm(se3.so3_log(t[:3, :3])))), float(np.linalg.norm(t[:3, 3]))


def test_a_brain_moved_off_the_plane_is_moved_back() -> None:
    volume, g = moved([0.0, 3.0, -2.5], [2.0, 0.0, 0.0])            # a shift along x, turns about y and z
    fit = midline_fit(volume, plane_x_mm=0.0)
    assert fit.applied and 3.3 < fit.rotation_deg < 4.5
    rot, shift = size(fit.correction @ g)                          # back where the symmetric brain was
    assert rot < 0.4 and shift < 0.3, (rot, shift)
    assert fit.report()["applied"] is True


def test_a_move_along_the_plane_is_left_to_the_network() -> None:
    volume, _ = moved([5.0, 0.0, 0.0], [0.0, 4.0, -3.0])            # a turn about x, shifts in y and z
    fit = midline_fit(volume, plane_x_mm=0.0)
    rot, shift = size(fit.correction)
    assert rot < 0.4 and shift < 0.3, (rot, shift)


def test_an_implausible_correction_is_reported_not_applied() -> None:
    volume, _ = moved([0.0, 2.0 * MAX_ROTATION_DEG, 0.0], [0.0, 0.0, 0.0])
    fit = midline_fit(volume, plane_x_mm=0.0)
    assert not fit.applied and fit.rotation_deg > MAX_ROTATION_DEG and np.array_equal(fit.correction, np.eye(4))
    assert not midline_fit(Volume(np.zeros((8, 8, 8), np.float32), np.eye(4)), 0.0).applied


def test_a_registration_that_gives_up_leaves_the_volume_as_it_is(monkeypatch) -> None:  # noqa: ANN001
    def gives_up(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise RuntimeError("All samples map outside moving image buffer")

    monkeypatch.setattr(midline, "register_rigid", gives_up)
    volume, _ = moved([0.0, 3.0, 0.0], [0.0, 0.0, 0.0])
    fit = midline.midline_fit(volume, plane_x_mm=0.0)
    assert not fit.applied and np.array_equal(fit.correction, np.eye(4))


def test_a_volume_whose_stacks_do_not_predict_each_other_is_not_turned(monkeypatch) -> None:  # noqa: ANN001
    volume, _ = moved([0.0, 3.0, 0.0], [0.0, 0.0, 0.0])
    assert midline_fit(volume, 0.0, held_out_ncc=0.9).applied
    monkeypatch.setattr(midline, "register_rigid", lambda *a, **k: pytest.fail("no registration is needed"))
    fit = midline_fit(volume, 0.0, held_out_ncc=quality.MIN_HELD_OUT_NCC - 0.3)
    assert not fit.applied and np.array_equal(fit.correction, np.eye(4))
