"""The reconstruction's atlas frame re-estimated from slices re-cut from it, against a known frame error."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from service.geometry import se3, twin
from service.geometry.pose import make_pose
from service.inference.estimator import PoseEstimate
from service.io.volume import Volume
from service.reconstruction import atlas_frame as af
from tests.support.phantoms import phantom_brain

FRAME_ERROR = make_pose(se3.so3_exp(np.radians([3.0, -2.0, 4.0])), np.array([2.5, -1.5, 3.0]))   # atlas <- recon


class Oracle:
    """Poses each re-cut slice where it truly lies in the atlas (``FRAME_ERROR`` @ its cut pose); a
    share of them on the other twin (a single slice cannot tell) and a share far off (junk)."""

    info = type("Info", (), {"pixel_spacing_mm": 2.0, "input_size": 48})()

    def __init__(self, twins: float, junk: float) -> None:
        self.cut: np.ndarray | None = None
        self.twins, self.junk = twins, junk

    def estimate(self, inputs: np.ndarray, mc_samples: int) -> PoseEstimate:
        rng = np.random.default_rng(3)
        truth = FRAME_ERROR[None] @ self.cut
        out = np.where((rng.random(len(truth)) < self.twins)[:, None, None], twin.twin(truth, 0.0), truth)
        bad = rng.random(len(truth)) < self.junk
        out[bad] = out[bad] @ se3.exp(rng.normal(0, 1, (int(bad.sum()), 6)) * [0.5, 0.5, 0.5, 20, 20, 20])
        return PoseEstimate(out, np.ones(len(out)), np.zeros(len(out), bool), spread_mm=np.full(len(out), 5.0))


@pytest.fixture(scope="module")
def brain() -> Volume:
    image, _, affine = phantom_brain(0)
    return Volume(image.astype(np.float32), affine)


@pytest.mark.parametrize(("twins", "junk"), [(0.0, 0.0), (0.5, 0.25)])
def test_the_frame_error_is_found_through_twins_and_junk(brain: Volume, monkeypatch: pytest.MonkeyPatch,
                                                         twins: float, junk: float) -> None:
    oracle = Oracle(twins, junk)
    real_recut, real_preprocess = af.recut, af.preprocess_slices
    cut = {}

    def recut(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        images, masks, poses, centre = real_recut(*args, **kwargs)
        cut["poses"] = poses
        return images, masks, poses, centre

    def preprocess(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        prep = real_preprocess(*args, **kwargs)
        keep = prep.mask_fraction >= af.MIN_MASK_FRACTION
        oracle.cut = af.sampling.recentre(cut["poses"], prep.centroid_mm)[keep]
        return prep

    monkeypatch.setattr(af, "recut", recut)
    monkeypatch.setattr(af, "preprocess_slices", preprocess)
    fit = af.atlas_frame(brain, oracle, 0.0, n_slices=96)
    assert fit.applied and fit.slices >= 80
    moved = fit.correction @ np.linalg.inv(FRAME_ERROR)
    assert np.degrees(np.linalg.norm(se3.so3_log(moved[:3, :3]))) < 0.05
    assert np.linalg.norm(fit.correction[:3, 3] - FRAME_ERROR[:3, 3]) < 0.05
    assert fit.rotation_deg == pytest.approx(np.degrees(np.linalg.norm(se3.so3_log(FRAME_ERROR[:3, :3]))), abs=0.05)


def test_an_implausible_correction_is_reported_not_applied(brain: Volume, monkeypatch: pytest.MonkeyPatch) -> None:
    class Lost(Oracle):
        def estimate(self, inputs: np.ndarray, mc_samples: int) -> PoseEstimate:
            n = len(inputs)
            far = make_pose(se3.so3_exp(np.array([0.0, 0.0, 1.0])), np.array([40.0, 0.0, 0.0]))
            return PoseEstimate(np.repeat(far[None], n, 0), np.ones(n), np.zeros(n, bool), spread_mm=np.full(n, 5.0))

    fit = af.atlas_frame(brain, Lost(0.0, 0.0), 0.0, n_slices=48)
    assert not fit.applied and np.array_equal(fit.correction, np.eye(4)) and fit.rotation_deg > af.MAX_ROTATION_DEG
    assert fit.report()["applied"] is False


def test_no_frame_is_sought_where_the_stacks_do_not_predict_each_other(brain: Volume) -> None:
    """A job whose leave-one-stack-out NCC is under the midline's floor gets no frame step: the
    estimator is never asked."""
    class Unasked(Oracle):
        def estimate(self, inputs: np.ndarray, mc_samples: int) -> PoseEstimate:
            raise AssertionError("the frame step posed slices of an incoherent volume")

    for barely in (0.42, 0.6):                  # 0.6: coherent, but as whole-uterus scenes moved the wrong way
        fit = af.atlas_frame(brain, Unasked(0.0, 0.0), 0.0, n_slices=48, held_out_ncc=barely)
        assert not fit.applied and np.array_equal(fit.correction, np.eye(4)) and fit.report()["applied"] is False


def test_the_correction_moves_the_volume_and_every_slice_together() -> None:
    """``with_frame``: after the correction a slice pixel and the volume voxel it was reconstructed
    from still coincide, both now where the correction puts them in the atlas."""
    from dataclasses import dataclass

    vol = Volume(np.zeros((4, 4, 4), np.float32), np.diag([1.5, 1.5, 1.5, 1.0]))
    slice_from_voxel = make_pose(se3.so3_exp(np.array([0.1, 0.2, 0.3])), np.array([3.0, -2.0, 5.0]))

    @dataclass
    class Result:
        volume: Volume
        atlas_from_voxel_final: np.ndarray

    result = Result(vol, slice_from_voxel[None])
    pixel = np.array([1.0, 2.0, 0.0, 1.0])
    voxel = np.linalg.solve(vol.affine, slice_from_voxel @ pixel)          # where the pixel sits in the volume
    moved = af.with_frame(result, af.FrameFit(FRAME_ERROR, True))
    np.testing.assert_allclose(moved.atlas_from_voxel_final[0] @ pixel, FRAME_ERROR @ slice_from_voxel @ pixel)
    np.testing.assert_allclose(moved.volume.affine @ voxel, moved.atlas_from_voxel_final[0] @ pixel, atol=1e-9)
    assert af.with_frame(result, af.FrameFit(FRAME_ERROR, False)) is result


def test_a_masks_extent_along_any_normal_is_that_of_its_surface_voxels() -> None:
    rng = np.random.default_rng(3)
    mask = np.zeros((30, 30, 30), bool)
    mask[5:25, 8:22, 10:20] = True
    mask[12:18, 2:28, 12:16] = True                  # not convex: a bar through a box
    mask &= rng.random(mask.shape) > 0.05            # holes inside, a ragged surface
    points = np.argwhere(mask).astype(float)
    surface = np.argwhere(mask & ~ndimage.binary_erosion(mask)).astype(float)
    normals = rng.normal(size=(40, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    lo, hi = af.extent_along(surface, normals, block=7)
    along = points @ normals.T
    assert len(surface) < len(points)
    np.testing.assert_allclose(lo, along.min(axis=0), atol=1e-12)
    np.testing.assert_allclose(hi, along.max(axis=0), atol=1e-12)
