"""Outputs: ITK .tfm round trip through SimpleITK, the per-slice listing, report, volume and preview."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import SimpleITK as sitk
from PIL import Image

from service.geometry import frames, se3
from service.geometry.pose import apply
from service.io.volume import Volume, read_volume, to_sitk
from service.reconstruction.export import scanner_from_atlas, write_outputs
from service.reconstruction.pipeline import reconstruct
from service.reconstruction.preview import GAP_PX, LABEL_PX, atlas_planes, preview_png, window
from tests.reconstruction.helpers import perturb


@pytest.fixture(scope="module")
def written(acquisition, tmp_path_factory):
    truth = acquisition.slice_set()
    start = perturb(truth.atlas_from_voxel, np.random.default_rng(2), 1.0, 1.0, truth.centres())
    include = [np.ones(len(t), bool) for t in acquisition.truth]
    include[1][3] = False
    ss = acquisition.slice_set(poses=np.split(start, [20, 40]), include=include)
    result = reconstruct(ss, resolution_mm=1.5, svr_iterations=1)
    folder = tmp_path_factory.mktemp("outputs")
    summary = write_outputs(result, ss, folder)
    return ss, result, folder, summary


def test_tfm_round_trips_through_simpleitk(acquisition, written):
    """(f) Each .tfm, read by SimpleITK, maps a slice voxel's atlas position (LPS) to that voxel's
    physical point in the stack file (LPS), i.e. fixed = atlas, moving = stack."""
    ss, result, folder, _ = written
    rng = np.random.default_rng(0)
    for i in rng.choice(np.flatnonzero(ss.include), 6, replace=False):
        s, k = int(ss.stack_index[i]), int(ss.slice_index[i])
        tfm = sitk.ReadTransform(str(folder / "transforms" / f"stack{s}_slice{k:03d}.tfm"))
        stack_image = to_sitk(acquisition.stacks[s][0])
        voxels = ss.voxel[ss.slice_id == i][:5].astype(np.float64)
        atlas_ras = apply(result.atlas_from_voxel_final[i], voxels)
        for v, p in zip(voxels, atlas_ras):
            mapped = tfm.TransformPoint(tuple(float(c) for c in frames.LPS_FROM_RAS[:3, :3] @ p))
            expected = stack_image.TransformContinuousIndexToPhysicalPoint(tuple(float(c) for c in v))
            assert np.allclose(mapped, expected, atol=1e-6)
        # and the matrix is F (stack_affine @ inv(atlas_from_voxel)) F
        m = np.eye(4)
        m[:3, :3] = np.array(tfm.GetParameters()[:9]).reshape(3, 3)
        m[:3, 3] = tfm.GetParameters()[9:]
        want = frames.lps_transform_from_ras(scanner_from_atlas(result.atlas_from_voxel_final[i], ss.stack_affine[i]))
        assert np.allclose(m, want, atol=1e-9)


def test_listing_report_volume_and_preview(written):
    ss, result, folder, summary = written
    lines = (folder / "transforms" / "slice_transforms.txt").read_text().splitlines()
    assert lines[0].startswith("#") and len(lines) == ss.n_slices + 1
    rows = np.array([[float(v) for v in line.split()] for line in lines[1:]])
    assert rows.shape == (ss.n_slices, 16)
    assert np.array_equal(rows[:, 0], ss.stack_index) and np.array_equal(rows[:, 1], ss.slice_index)
    assert np.array_equal(rows[:, 2].astype(bool), result.included)
    assert np.allclose(rows[:, 4:].reshape(-1, 3, 4), result.atlas_from_voxel_final[:, :3, :], rtol=1e-8, atol=1e-6)
    assert len(list((folder / "transforms").glob("*.tfm"))) == ss.n_slices

    report = json.loads((folder / "report.json").read_text())
    assert report["n_slices"] == ss.n_slices == len(report["slices"])
    assert report["intensity"] == result.intensity.summary(result.included)     # equal gains: about 1
    assert 0 < report["intensity"]["slices"] <= report["n_included"]
    assert 0.8 < report["intensity"]["gain_p5_p95"][0] <= 1.0 <= report["intensity"]["gain_p5_p95"][1] < 1.25
    entry = report["slices"][20 + 3]
    assert (entry["stack"], entry["slice"], entry["included"], entry["ncc"]) == (1, 3, False, None)
    assert summary["n_not_used"] >= 1 and summary["n_included"] == int(result.included.sum())
    assert summary == report                       # the job record holds the same report, per-slice included

    vol = read_volume(folder / "volume.nii.gz")
    assert np.allclose(vol.affine, result.volume.affine) and np.allclose(vol.array, result.volume.array)
    # atlas coordinates, not the scanner's: NIfTI's aligned-anatomy code, and nibabel (FSL's rule) places it alike
    import nibabel
    header = nibabel.load(folder / "volume.nii.gz").header
    assert (int(header["qform_code"]), int(header["sform_code"])) == (2, 2)
    assert np.allclose(header.get_best_affine(), result.volume.affine, atol=1e-4)
    png = Image.open(folder / "preview.png")
    i, j, k = result.volume.array.shape
    assert png.size == (j + i + i + 2 * GAP_PX, max(k, j) + LABEL_PX) and png.mode == "L"


def test_preview_handles_anisotropic_and_empty_volumes():
    vol = Volume(np.random.default_rng(0).random((10, 12, 6)).astype(np.float32), np.diag([1.0, 1.0, 2.0, 1.0]))
    img = Image.open(io.BytesIO(preview_png(vol)))
    assert img.size == (12 + 10 + 10 + 2 * GAP_PX, 12 + LABEL_PX)      # k stretched to 12 mm of 1 mm pixels
    blank = Image.open(io.BytesIO(preview_png(Volume(np.zeros((4, 4, 4), np.float32), np.eye(4)))))
    assert np.asarray(blank)[:4].max() == 0                   # nothing in the panels; the strip names their sides


def test_the_previews_strip_names_the_sides_and_draws_a_10_mm_bar() -> None:
    """Below the panels: a letter at each panel's edges, neighbouring panels' letters apart (a gap with
    a grey rule between them) and, under the first panel, a bar of 10 mm (20 pixels of 0.5 mm voxels,
    10 of 1 mm ones)."""
    for voxel_mm, bar_px in ((0.5, 20), (1.0, 10)):
        vol = Volume(np.ones((40, 48, 32), np.float32), np.diag([voxel_mm] * 3 + [1.0]))
        strip = np.asarray(Image.open(io.BytesIO(preview_png(vol))))[-LABEL_PX:]
        assert (strip[LABEL_PX // 2, 8:41] == 255).sum() == bar_px      # between the letters
        starts = np.cumsum([0, 48 + GAP_PX, 40 + GAP_PX])
        for start, width in zip(starts, (48, 40, 40)):
            for edge in (slice(start, start + 7), slice(start + width - 7, start + width)):
                assert strip[:, edge].max() > 128                 # a letter at both edges of every panel
        for start in starts[1:]:
            assert 0 < strip[:, start - GAP_PX:start].max() < 128       # the rule between two panels, no letter


def _world_object(affine: np.ndarray, shape: tuple[int, int, int]) -> Volume:
    """A bar along atlas x and a ball above it (atlas mm about the grid's centre) sampled on ``affine``'s voxels."""
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    p = ijk @ affine[:3, :3].T + affine[:3, 3]
    bar = (np.abs(p[..., 1]) < 3) & (np.abs(p[..., 2]) < 3) & (np.abs(p[..., 0]) < 20)
    ball = np.linalg.norm(p - [0.0, 0.0, 12.0], axis=-1) < 5
    return Volume((bar * 100.0 + ball * 200.0 + 1.0).astype(np.float32), affine)


def test_the_preview_cuts_atlas_planes_whatever_the_grids_orientation() -> None:
    shape = (48, 48, 48)
    aligned = np.diag([1.0, 1.0, 1.0, 1.0])
    aligned[:3, 3] = -23.5
    turned = aligned.copy()
    turned[:3, :3] = se3.so3_exp(np.radians([8.0, -6.0, 15.0]))              # a job's frame correction
    turned[:3, 3] = -turned[:3, :3] @ [23.5, 23.5, 23.5]                       # about the same centre
    straight, tilted = atlas_planes(_world_object(aligned, shape)), atlas_planes(_world_object(turned, shape))
    # On an aligned grid of cubic voxels the panels are the array's own mid-planes, as laid out before.
    w = window(_world_object(aligned, shape).array)
    np.testing.assert_array_equal(straight[2], w[:, :, 24].T[::-1])
    np.testing.assert_array_equal(straight[0], w[24, :, :].T[::-1])
    # Turned by 15 deg, the same atlas planes show the same anatomy (the array's mid-plane would not).
    for a, b in zip(straight, tilted):
        h, w_ = min(a.shape[0], b.shape[0]), min(a.shape[1], b.shape[1])
        ca, cb = (x[(x.shape[0] - h) // 2:][:h, (x.shape[1] - w_) // 2:][:, :w_] for x in (a, b))   # centres
        assert np.corrcoef(ca.ravel(), cb.ravel())[0, 1] > 0.85
    axial_rows = tilted[2].astype(float).sum(axis=1)
    assert abs(int(np.argmax(axial_rows)) - tilted[2].shape[0] // 2) <= 2   # the bar lies along the rows' middle
    raw_mid = window(_world_object(turned, shape).array)[:, :, 24].T[::-1]
    assert np.corrcoef(raw_mid.ravel(), straight[2].ravel())[0, 1] < 0.85
