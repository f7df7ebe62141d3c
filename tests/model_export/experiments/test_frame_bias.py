"""The frame-bias experiment's geometry: the common frame of an acquisition's errors, the rigid
registration that says where a brain's neighbours put it, and a brain's midline against the atlas
plane, against transforms simulated here."""

from __future__ import annotations

import numpy as np

from model_export.atlas import AtlasVolume
from model_export.experiments.frame_bias import as_row, common_frame, midline_offset, register_rigid
from service.geometry import se3
from service.geometry.pose import make_pose, translate
from tests.support.phantoms import phantom_brain, symmetric_phantom_brain


def test_a_common_error_about_the_centre_is_found_and_undone() -> None:
    """Poses all moved by one rigid error ``G`` (applied about the brain's centre): the frame is ``G``
    about that centre, and undoing it leaves no error."""
    rng = np.random.default_rng(0)
    centre = np.array([4.0, -6.0, 10.0])
    truth = se3.exp(np.concatenate([rng.normal(0, 0.5, (20, 3)), rng.normal(0, 20, (20, 3))], axis=1))
    g = se3.exp(np.array([0.03, -0.02, 0.05, 1.5, -2.0, 0.5]))
    moved = translate(centre) @ g @ se3.inverse(translate(centre)) @ truth
    frame, left = common_frame(moved, truth, centre)
    assert np.allclose(frame, g, atol=1e-6) and left.max() < 1e-6
    assert np.allclose(as_row(frame)[3:], g[:3, 3]) and np.isclose(np.linalg.norm(as_row(frame)[:3]),
                                                                     np.degrees(np.linalg.norm(se3.so3_log(g[:3, :3]))))


def test_registration_recovers_a_brain_moved_by_a_known_rigid_transform() -> None:
    """The phantom brain and the same brain moved in the world by ``P`` (4 deg, 3 mm): the registration
    maps each point of the first to the same anatomy in the second, i.e. returns ``P``."""
    image, mask, affine = phantom_brain(2)
    fixed = AtlasVolume("fixed", "test", image, mask, affine)
    p = make_pose(se3.so3_exp(np.radians([2.0, -3.0, 1.5])), [0.0, 0.0, 0.0])
    p = translate(fixed.centre) @ p @ se3.inverse(translate(fixed.centre)) @ translate([2.0, -1.5, 1.8])
    moving = AtlasVolume("moving", "test", image, mask, p @ affine)
    found = register_rigid(fixed, moving)
    error = se3.inverse(found) @ p
    assert np.degrees(np.linalg.norm(se3.so3_log(error[:3, :3]))) < 0.5
    assert np.linalg.norm(error[:3, :3] @ fixed.centre + error[:3, 3] - fixed.centre) < 0.5


def symmetric_brain() -> AtlasVolume:
    """The phantom brain made mirror-symmetric about the atlas plane ``x = 0``."""
    return AtlasVolume("symmetric", "test", *symmetric_phantom_brain(3))


def moved(volume: AtlasVolume, rot_deg: list[float], shift_mm: list[float]) -> tuple[AtlasVolume, np.ndarray]:
    """``volume`` moved in the world by a rigid ``g`` about its centre; returns it and ``g``."""
    g = make_pose(se3.so3_exp(np.radians(rot_deg)), shift_mm)
    about = translate(volume.centre)
    return AtlasVolume("moved", "test", volume.image, volume.mask, about @ g @ se3.inverse(about) @ volume.affine), g


def test_a_brain_moved_off_the_atlas_plane_is_brought_back_by_its_midline_offset() -> None:
    """A symmetric brain moved by ``g`` (a shift along x, turns about y and z: what a mirror sees) has
    midline offset ``g^-1``; moved along the plane (a turn about x, shifts in y and z), none."""
    brain = symmetric_brain()
    off, g = moved(brain, [0.0, 3.0, -2.0], [2.0, 0.0, 0.0])
    error = midline_offset(off) @ g
    assert np.degrees(np.linalg.norm(se3.so3_log(error[:3, :3]))) < 0.5 and np.linalg.norm(error[:3, 3]) < 0.3
    along, _ = moved(brain, [4.0, 0.0, 0.0], [0.0, 3.0, -2.0])
    h = midline_offset(along)
    assert np.degrees(np.linalg.norm(se3.so3_log(h[:3, :3]))) < 0.5 and np.linalg.norm(h[:3, 3]) < 0.3
