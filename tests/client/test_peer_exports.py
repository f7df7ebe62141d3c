"""`svrnet export` against a simulated truth: every exported slice lies where its pose puts it, as
NeSVoR (nibabel, the slice file's affine) and NiftyMIC (SimpleITK: the .tfm composed with the stack
file's own placement) read it."""

from __future__ import annotations

import json
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from client import cli
from client.errors import UnusableInput
from client.peer_exports import export

SHAPE = (20, 16, 6)
F = np.diag([-1.0, -1.0, 1.0, 1.0])


@pytest.fixture
def case(tmp_path: Path) -> dict:
    """A left-handed oblique stack file, its mask, and an answer placing each slice by a pose of its own
    (a rigid move per slice, as motion gives): slice 0 without brain, slice 3 not accepted."""
    rng = np.random.default_rng(4)
    scanner_from_voxel = np.eye(4)
    scanner_from_voxel[:3, :3] = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix() @ np.diag([-1.1, 0.9, 3.2])
    scanner_from_voxel[:3, 3] = (-12.0, 30.0, 5.0)
    data = rng.random(SHAPE).astype(np.float32) * 100
    mask = (rng.random(SHAPE) > 0.5).astype(np.uint8)
    stack, mask_path = tmp_path / "ax.nii.gz", tmp_path / "ax_mask.nii.gz"
    for values, path in ((data, stack), (mask, mask_path)):
        image = nib.Nifti1Image(values, scanner_from_voxel)
        image.set_qform(scanner_from_voxel, 1)
        nib.save(image, path)
    poses, slices = [], []
    for k in range(SHAPE[2]):
        move = np.eye(4)
        move[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.2, 3)).as_matrix()
        move[:3, 3] = rng.normal(0, 10.0, 3)
        poses.append(move @ scanner_from_voxel)
        slices.append({"index": k, "atlas_from_voxel": poses[-1].tolist(), "accepted": k not in (0, 3),
                       "reason": "empty" if k == 0 else "high_expected_error" if k == 3 else None, "expected_error_mm": 2.5})
    answer = {"stacks": [{"index": 0, "filename": "ax.nii.gz", "shape": list(SHAPE),
                          "scanner_from_voxel": scanner_from_voxel.tolist(), "slices": slices}]}
    return {"stack": stack, "mask": mask_path, "data": data, "mask_data": mask, "poses": poses, "answer": answer,
            "scanner_from_voxel": scanner_from_voxel}


def test_a_nesvor_slice_file_places_each_voxel_where_its_pose_does(case: dict, tmp_path: Path) -> None:
    out = tmp_path / "nesvor"
    assert export(case["answer"], [case["stack"]], [case["mask"]], out, "nesvor", thickness_mm=[2.5]) == 4
    rows = (out / "slices.tsv").read_text().splitlines()[1:]
    assert [int(r.split("\t")[3]) for r in rows] == [1, 2, 4, 5]                # accepted slices only
    ij = np.array([[0, 0], [19, 0], [7, 11], [19, 15]], np.float64)
    for i, k in enumerate([1, 2, 4, 5]):
        image, mask = nib.load(out / f"{i}.nii.gz"), nib.load(out / f"mask_{i}.nii.gz")
        assert image.shape == (20, 16, 1) and np.array_equal(np.asarray(image.dataobj)[..., 0], case["data"][:, :, k])
        assert np.array_equal(np.asarray(mask.dataobj)[..., 0], case["mask_data"][:, :, k])
        got = (image.affine @ np.c_[ij, np.zeros(4), np.ones(4)].T).T
        want = (case["poses"][k] @ np.c_[ij, np.full(4, k), np.ones(4)].T).T
        np.testing.assert_allclose(got, want, atol=1e-4)
        assert image.header.get_zooms()[2] == pytest.approx(2.5, abs=1e-5)       # the slice profile
        assert np.allclose(mask.affine, image.affine)
    assert len(list(out.glob("*.nii.gz"))) == 8


def test_a_niftymic_transform_composed_with_the_stack_file_gives_each_voxel_its_atlas_point(case: dict,
                                                                                          tmp_path: Path) -> None:
    """NiftyMIC reads the stack with SimpleITK (LPS) and corrects each slice's placement by T (slice.py:
    ``affine = T o A0``): T applied to a voxel's scanner point must give its atlas point."""
    sitk = pytest.importorskip("SimpleITK")
    out = tmp_path / "niftymic"
    assert export(case["answer"], [case["stack"]], None, out, "niftymic", all_slices=True) == 5     # not slice 0
    assert sorted(p.name for p in out.iterdir()) == [f"ax_slice{k}.tfm" for k in (1, 2, 3, 4, 5)]
    image = sitk.ReadImage(str(case["stack"]))
    for k in (1, 3, 5):
        t = sitk.ReadTransform(str(out / f"ax_slice{k}.tfm"))
        for i, j in ((0, 0), (19, 15), (5, 9)):
            scanner_lps = image.TransformContinuousIndexToPhysicalPoint((float(i), float(j), float(k)))
            atlas_lps = F @ case["poses"][k] @ np.array([i, j, k, 1.0])
            np.testing.assert_allclose(t.TransformPoint(scanner_lps), atlas_lps[:3], atol=1e-4)


def test_files_that_are_not_the_answers_are_refused(case: dict, tmp_path: Path) -> None:
    other = tmp_path / "ax.nii.gz"
    moved = case["scanner_from_voxel"].copy()
    moved[0, 3] += 5.0
    nib.save(nib.Nifti1Image(case["data"], moved), other)
    with pytest.raises(UnusableInput, match="not the file the answer's stack 0 was read from"):
        export(case["answer"], [other], None, tmp_path / "x", "niftymic")
    two = nib.Nifti1Image(case["data"], case["scanner_from_voxel"])
    two.set_qform(moved, 1)                                                      # qform and sform disagree
    nib.save(two, other)
    with pytest.raises(UnusableInput, match="qform and sform disagree"):
        export(case["answer"], [other], None, tmp_path / "x", "niftymic")
    with pytest.raises(UnusableInput, match="holds 1 stacks, 2 files"):
        export(case["answer"], [other, other], None, tmp_path / "x", "nesvor")


def test_the_cli_writes_and_says_what_to_run_next(case: dict, tmp_path: Path) -> None:
    answer = tmp_path / "poses.json"
    answer.write_text(json.dumps(case["answer"]))
    out = tmp_path / "slices"
    r = CliRunner().invoke(cli.app, ["export", str(answer), str(case["stack"]), "--to", "nesvor", "--out-dir", str(out),
                                     "--mask", str(case["mask"])], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert "wrote 4 slices for nesvor" in r.stdout and f"nesvor reconstruct --input-slices {out}" in r.stdout
    assert "no --mask" not in r.stderr
    r = CliRunner().invoke(cli.app, ["export", str(answer), str(case["stack"]), "--to", "nesvor", "--out-dir",
                                     str(tmp_path / "bare")], env={"COLUMNS": "200"})
    assert r.exit_code == 0 and "no --mask: NeSVoR takes every pixel" in r.stderr
    r = CliRunner().invoke(cli.app, ["export", str(answer), str(case["stack"]), "--to", "svrtk", "--out-dir", str(out)])
    assert r.exit_code == 2 and "--to" in r.output
    answer.write_text("{not json")
    r = CliRunner().invoke(cli.app, ["export", str(answer), str(case["stack"]), "--to", "nesvor", "--out-dir", str(out)])
    assert r.exit_code == 5 and "poses.json is not a JSON answer" in r.output
