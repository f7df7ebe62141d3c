"""`svrnet export` against a simulated truth: every exported slice lies where its pose puts it, as
NeSVoR (nibabel, the slice file's affine) and NiftyMIC (SimpleITK: the .tfm composed with the stack
file's own placement) read it."""

from __future__ import annotations

import json
import re
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from client import cli
from client.errors import ArgumentError, UnusableInput
from client.peer_exports import export

SHAPE = (20, 16, 6)
F = np.diag([-1.0, -1.0, 1.0, 1.0])


def make_case(folder: Path, slice_axis: int = 2) -> dict:
    """A left-handed oblique stack file whose slices lie along ``slice_axis``, its mask, and an answer
    placing each slice by a pose of its own (a rigid move per slice, as motion gives): slice 0 without
    brain, slice 3 not accepted."""
    rng = np.random.default_rng(4)
    shape, zooms = list(SHAPE[:2]), [-1.1, 0.9]
    shape.insert(slice_axis, SHAPE[2])
    zooms.insert(slice_axis, 3.2)
    scanner_from_voxel = np.eye(4)
    scanner_from_voxel[:3, :3] = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix() @ np.diag(zooms)
    scanner_from_voxel[:3, 3] = (-12.0, 30.0, 5.0)
    data = rng.random(shape).astype(np.float32) * 100
    mask = (rng.random(shape) > 0.5).astype(np.uint8)
    stack, mask_path = folder / "ax.nii.gz", folder / "ax_mask.nii.gz"
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
    answer = {"stacks": [{"index": 0, "filename": "ax.nii.gz", "shape": shape, "slice_axis": slice_axis,
                          "scanner_from_voxel": scanner_from_voxel.tolist(), "slices": slices}]}
    return {"stack": stack, "mask": mask_path, "data": data, "mask_data": mask, "poses": poses, "answer": answer,
            "scanner_from_voxel": scanner_from_voxel, "slice_axis": slice_axis}


@pytest.fixture
def case(tmp_path: Path) -> dict:
    return make_case(tmp_path)


def voxel(slice_axis: int, in_plane: tuple[float, float], k: float) -> list[float]:
    """The stack's voxel index of in-plane position ``in_plane`` (the two other axes in cyclic order
    after ``slice_axis``) on slice ``k``: what a slice file's voxel ``(u, v, 0)`` holds."""
    index = [0.0, 0.0, 0.0]
    index[(slice_axis + 1) % 3], index[(slice_axis + 2) % 3], index[slice_axis] = in_plane[0], in_plane[1], k
    return index


@pytest.mark.parametrize("slice_axis", [2, 0, 1])
def test_a_nesvor_slice_file_places_each_voxel_where_its_pose_does(slice_axis: int, tmp_path: Path) -> None:
    """Whatever axis the file stores its slices along, a slice file holds that slice's pixels and
    places each where the slice's pose puts the stack voxel it came from."""
    case = make_case(tmp_path, slice_axis)
    out = tmp_path / "nesvor"
    assert export(case["answer"], [case["stack"]], [case["mask"]], out, "nesvor", thickness_mm=[2.5]).count == 4
    rows = (out / "slices.tsv").read_text().splitlines()[1:]
    assert [int(r.split("\t")[3]) for r in rows] == [1, 2, 4, 5]                # accepted slices only
    uv = [(0, 0), (15, 0), (7, 11), (15, 15)]
    in_plane = tuple(case["data"].shape[(slice_axis + j) % 3] for j in (1, 2))
    for i, k in enumerate([1, 2, 4, 5]):
        image, mask = nib.load(out / f"{i}.nii.gz"), nib.load(out / f"mask_{i}.nii.gz")
        assert image.shape == (*in_plane, 1)
        for u, v in uv:
            index = tuple(int(x) for x in voxel(slice_axis, (u, v), k))
            assert np.asarray(image.dataobj)[u, v, 0] == case["data"][index]
            assert np.asarray(mask.dataobj)[u, v, 0] == case["mask_data"][index]
        got = (image.affine @ np.c_[uv, np.zeros(4), np.ones(4)].T).T
        want = (case["poses"][k] @ np.c_[[voxel(slice_axis, p, k) for p in uv], np.ones(4)].T).T
        np.testing.assert_allclose(got, want, atol=1e-4)
        assert image.header.get_zooms()[2] == pytest.approx(2.5, abs=1e-5)       # the slice profile
        assert np.linalg.det(image.affine[:3, :3]) < 0                          # the file's handedness kept
        assert np.allclose(mask.affine, image.affine)
    assert len(list(out.glob("*.nii.gz"))) == 8


def test_an_answer_without_slice_axis_is_cut_along_the_files_slice_axis_and_its_mask_in_any_storage(
        tmp_path: Path) -> None:
    """Poses a client made may leave out ``slice_axis``: the slices are cut along the file's axis of
    largest spacing, as the service cuts them, not along a default. A mask stored with the stack's
    axes in another order is brought onto the stack's voxels; one of another grid is refused."""
    case = make_case(tmp_path, slice_axis=0)
    answer = json.loads(json.dumps(case["answer"]))
    del answer["stacks"][0]["slice_axis"]
    stored = nib.Nifti1Image(np.transpose(case["mask_data"], (2, 1, 0)), case["scanner_from_voxel"] @ np.eye(4)[[2, 1, 0, 3]])
    permuted = tmp_path / "ax_mask_permuted.nii.gz"
    nib.save(stored, permuted)
    out = tmp_path / "nesvor"
    assert export(answer, [case["stack"]], [permuted], out, "nesvor").count == 4
    for i, k in enumerate([1, 2, 4, 5]):
        image, mask = nib.load(out / f"{i}.nii.gz"), nib.load(out / f"mask_{i}.nii.gz")
        assert image.shape == (*case["data"].shape[1:], 1)
        np.testing.assert_array_equal(np.asarray(image.dataobj)[..., 0], case["data"][k])
        np.testing.assert_array_equal(np.asarray(mask.dataobj)[..., 0], case["mask_data"][k])
    shifted = case["scanner_from_voxel"].copy()
    shifted[:3, 3] += shifted[:3, 1]                                       # one voxel along the second axis
    nib.save(nib.Nifti1Image(case["mask_data"], shifted), tmp_path / "off.nii.gz")
    with pytest.raises(UnusableInput, match="off.nii.gz is not on its stack's grid"):
        export(case["answer"], [case["stack"]], [tmp_path / "off.nii.gz"], tmp_path / "x", "nesvor")


def _header_variants(case: dict, folder: Path) -> dict[str, tuple[Path, Path]]:
    """The stack, and its mask, as files ITK reads otherwise than the service: pixdim of 1 mm where the
    sform says 1.1 / 0.9 / 3.2 (ITK takes pixdim), a qform 5 mm from the sform (ITK takes the qform),
    NIfTI-2 (SimpleITK reads none)."""
    pixdim = nib.Nifti1Image(case["data"], case["scanner_from_voxel"])
    pixdim.set_qform(None, 0)
    pixdim.header.set_zooms((1.0, 1.0, 1.0))
    pixdim.set_sform(case["scanner_from_voxel"], 1)
    moved = case["scanner_from_voxel"].copy()
    moved[0, 3] += 5.0
    qform = nib.Nifti1Image(case["data"], case["scanner_from_voxel"])
    qform.set_qform(moved, 1)
    kind = {"pixdim": nib.Nifti1Image, "qform": nib.Nifti1Image, "nifti2": nib.Nifti2Image}
    stacks = {"pixdim": pixdim, "qform": qform, "nifti2": nib.Nifti2Image(case["data"], case["scanner_from_voxel"])}
    paths = {}
    for name, image in stacks.items():
        (folder / name).mkdir(parents=True)
        paths[name] = folder / name / "ax.nii.gz", folder / name / "ax_mask.nii.gz"
        nib.save(image, paths[name][0])
        nib.save(kind[name](case["mask_data"], case["scanner_from_voxel"]), paths[name][1])
    return paths


@pytest.mark.parametrize("variant", ["pixdim", "qform", "nifti2"])
def test_a_file_itk_reads_otherwise_is_written_again_for_niftymic_where_the_service_placed_it(
        variant: str, case: dict, tmp_path: Path) -> None:
    """A stack ITK would place or size otherwise than the service (or not read) is given to NiftyMIC as
    a copy placed as the service placed it, its mask too where NiftyMIC could not read it: each slice
    NiftyMIC keeps lies where its pose puts it, on the mask's voxels."""
    sitk = pytest.importorskip("SimpleITK")
    path, mask = _header_variants(case, tmp_path / "in")[variant]
    out = tmp_path / "mc"
    done = export(case["answer"], [path], [mask], out, "niftymic")
    assert done.stacks == [out / "stacks" / "ax.nii.gz"]
    assert done.masks == [out / "masks" / "ax_mask.nii.gz" if variant == "nifti2" else mask]
    kept = _niftymic_slices(done.stacks[0], "ax", out)
    assert sorted(kept) == [1, 2, 4, 5]
    for k, placed in kept.items():
        for u, v in ((0, 0), (19, 15), (5, 9)):
            want = F @ case["poses"][k] @ np.array(voxel(2, (u, v), k) + [1.0])
            np.testing.assert_allclose((placed @ [u, v, 0, 1.0])[:3], want[:3], atol=1e-4)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(sitk.ReadImage(str(done.masks[0]), sitk.sitkUInt8)),
                                  np.transpose(case["mask_data"], (2, 1, 0)))
    assert export(case["answer"], [path], None, tmp_path / "n", "nesvor").count == 4     # NeSVoR reads our slices


@pytest.mark.parametrize("slice_axis", [2, 0])
def test_a_niftymic_transform_composed_with_the_stack_file_gives_each_voxel_its_atlas_point(slice_axis: int,
                                                                                          tmp_path: Path) -> None:
    """NiftyMIC reads the stack with SimpleITK (LPS), cuts it along its third axis, and corrects each
    slice's placement by T (slice.py: ``affine = T o A0``): T applied to a voxel's scanner point must
    give its atlas point. A stack stored with its slices along another axis is written again, slices
    last, with its mask; ``NAME.tfm`` is a rigid move among the slices' own."""
    sitk = pytest.importorskip("SimpleITK")
    case = make_case(tmp_path, slice_axis)
    out = tmp_path / "niftymic"
    done = export(case["answer"], [case["stack"]], [case["mask"]], out, "niftymic", all_slices=True)
    assert done.count == 5                                                             # not slice 0
    assert sorted(p.name for p in out.glob("*.tfm")) == ["ax.tfm"] + [f"ax_slice{k}.tfm" for k in (1, 2, 3, 4, 5)]
    stack = case["stack"] if slice_axis == 2 else out / "stacks" / "ax.nii.gz"
    assert done.stacks == [stack] and done.masks == [case["mask"] if slice_axis == 2 else out / "masks" / "ax_mask.nii.gz"]
    image = sitk.ReadImage(str(stack))
    assert image.GetSize() == (20, 16, 6)
    if slice_axis != 2:
        mask = sitk.GetArrayFromImage(sitk.ReadImage(str(done.masks[0])))       # [k, v, u]
        assert np.array_equal(mask[4, 11, 7], case["mask_data"][tuple(int(x) for x in voxel(slice_axis, (7, 11), 4))])
    for k in (1, 3, 5):
        t = sitk.ReadTransform(str(out / f"ax_slice{k}.tfm"))
        for u, v in ((0, 0), (19, 15), (5, 9)):
            scanner_lps = image.TransformContinuousIndexToPhysicalPoint((float(u), float(v), float(k)))
            atlas_lps = F @ case["poses"][k] @ np.array(voxel(slice_axis, (u, v), k) + [1.0])
            np.testing.assert_allclose(t.TransformPoint(scanner_lps), atlas_lps[:3], atol=1e-4)
    whole = sitk.ReadTransform(str(out / "ax.tfm"))
    matrix = np.array(sitk.AffineTransform(whole).GetMatrix()).reshape(3, 3)
    np.testing.assert_allclose(matrix @ matrix.T, np.eye(3), atol=1e-9)
    centre = image.TransformContinuousIndexToPhysicalPoint((9.5, 7.5, 2.5))
    moved = [sitk.ReadTransform(str(out / f"ax_slice{k}.tfm")).TransformPoint(centre) for k in range(1, 6)]
    assert np.linalg.norm(np.subtract(whole.TransformPoint(centre), np.mean(moved, axis=0))) < 5.0


def test_a_rigid_stacks_niftymic_transform_places_every_voxel_where_its_pose_does(case: dict, tmp_path: Path) -> None:
    """Where every slice has the same pose (a stack that did not move), ``NAME.tfm`` is that move: it
    takes each voxel's scanner point to its atlas point, as each slice's own transform does."""
    sitk = pytest.importorskip("SimpleITK")
    move = np.eye(4)
    move[:3, :3] = Rotation.from_rotvec([0.2, -0.4, 0.3]).as_matrix()
    move[:3, 3] = (7.0, -3.0, 12.0)
    pose = move @ case["scanner_from_voxel"]
    answer = json.loads(json.dumps(case["answer"]))
    for item in answer["stacks"][0]["slices"]:
        item["atlas_from_voxel"] = pose.tolist()
    out = tmp_path / "rigid"
    export(answer, [case["stack"]], [case["mask"]], out, "niftymic", all_slices=True)
    image = sitk.ReadImage(str(case["stack"]))
    for name in ("ax.tfm", "ax_slice2.tfm"):
        t = sitk.ReadTransform(str(out / name))
        for index in ((0, 0, 0), (19, 15, 5), (5, 9, 2)):
            scanner_lps = image.TransformContinuousIndexToPhysicalPoint(tuple(map(float, index)))
            np.testing.assert_allclose(t.TransformPoint(scanner_lps), (F @ pose @ [*index, 1.0])[:3], atol=1e-4)


def test_files_that_are_not_the_answers_are_refused(case: dict, tmp_path: Path) -> None:
    other = tmp_path / "ax.nii.gz"
    moved = case["scanner_from_voxel"].copy()
    moved[0, 3] += 5.0
    nib.save(nib.Nifti1Image(case["data"], moved), other)
    with pytest.raises(UnusableInput, match="not the file the answer's stack 0 was read from"):
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


def test_an_export_never_lies_among_an_earlier_one(case: dict, tmp_path: Path) -> None:
    """Each tool reads every slice file of its folder: a second patient's export into the first's folder
    is refused; with ``--overwrite`` none of the first's slices, masks or transforms is left, and
    nothing the export did not write is touched (a user's own stack named like a slice file, a
    ``stacks/`` folder of inputs); a folder holding the stacks exported, or slice files no export
    listed, is refused even then."""
    answer = tmp_path / "poses.json"
    answer.write_text(json.dumps(case["answer"]))
    out = tmp_path / "slices"
    run = lambda *more: CliRunner().invoke(cli.app, ["export", str(answer), str(case["stack"]), "--out-dir",  # noqa: E731
                                                     str(out), *more], env={"COLUMNS": "200"})
    assert run("--to", "nesvor", "--mask", str(case["mask"]), "--all-slices").exit_code == 0
    (out / "notes.txt").write_text("kept")
    (out / "stacks").mkdir()
    (out / "stacks" / "3_t2_haste.nii.gz").write_bytes(b"the user's own")
    before = sorted(p.name for p in out.iterdir())
    r = run("--to", "nesvor")
    assert r.exit_code == 2 and "not empty" in r.output and "--overwrite" in r.output     # a usage error, as predict's
    assert sorted(p.name for p in out.iterdir()) == before
    r = run("--to", "nesvor", "--overwrite")                                # accepted slices only, no masks now
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in out.iterdir()) == [".svrnet-export.json", "0.nii.gz", "1.nii.gz", "2.nii.gz",
                                                     "3.nii.gz", "notes.txt", "slices.tsv", "stacks"]
    assert (out / "stacks" / "3_t2_haste.nii.gz").read_bytes() == b"the user's own"
    r = run("--to", "niftymic", "--overwrite")
    assert r.exit_code == 0 and not list(out.glob("[0-9]*.nii.gz")) and not (out / "slices.tsv").exists(), r.output
    assert len(list(out.glob("ax_slice*.tfm"))) == 4 and (out / "stacks" / "3_t2_haste.nii.gz").exists()
    (out / ".svrnet-export.json").unlink()                                 # slice files no export listed
    r = run("--to", "nesvor", "--overwrite")
    assert r.exit_code == 2 and "no export of svrnet wrote" in r.output, r.output
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    (inputs / "ax.nii.gz").write_bytes(case["stack"].read_bytes())
    r = CliRunner().invoke(cli.app, ["export", str(answer), str(inputs / "ax.nii.gz"), "--to", "nesvor", "--out-dir",
                                     str(tmp_path), "--overwrite"], env={"COLUMNS": "200"})
    assert r.exit_code == 2 and "lies in the folder to write" in r.output and (inputs / "ax.nii.gz").exists()


def test_a_jobs_refined_poses_are_exported_by_the_jobs_verdict(case: dict, tmp_path: Path) -> None:
    """Of a job's refined poses, the slices the job reconstructed from (``included``) are written, with
    their refined expected errors, whatever the prediction first said of them."""
    refined = json.loads(json.dumps(case["answer"]))
    for s in refined["stacks"][0]["slices"]:
        s["included"] = s["index"] in (1, 3)                        # the job took slice 3, left the others out
        s["refined_expected_error_mm"] = 1.25
    done = export(refined, [case["stack"]], None, tmp_path / "out", "nesvor")
    rows = (tmp_path / "out" / "slices.tsv").read_text().splitlines()[1:]
    assert done.count == 2 and [r.split("\t")[3] for r in rows] == ["1", "3"]
    assert all(r.endswith("\t1\t1.250") for r in rows)


def test_the_slices_a_job_placed_beside_its_volume_are_exported_within_the_answers_limit(case: dict,
                                                                                        tmp_path: Path) -> None:
    """A slice the job placed by its stack's motion or by its volume is written where its refined
    expected error is within the answer's ``max_expected_error_mm``, and not beyond it."""
    refined = json.loads(json.dumps(case["answer"]))
    refined["max_expected_error_mm"] = 4.8
    for s in refined["stacks"][0]["slices"]:
        s.update(included=s["index"] == 1, placed_by_stack_motion=s["index"] == 2, placed_by_volume=s["index"] == 3,
                 refined_expected_error_mm={1: 1.5, 2: 3.0, 3: 6.0}.get(s["index"], 9.0))
    done = export(refined, [case["stack"]], None, tmp_path / "out", "nesvor")
    rows = (tmp_path / "out" / "slices.tsv").read_text().splitlines()[1:]
    assert done.count == 2 and [r.split("\t")[3] for r in rows] == ["1", "2"]
    assert [r.split("\t")[4] for r in rows] == ["1", "1"]


def test_the_cli_names_the_stacks_niftymic_must_read(tmp_path: Path) -> None:
    """A stack stored with its slices first is given to NiftyMIC as its rewritten copy, masks too; a
    file name NiftyMIC's pattern would not match is named."""
    case = make_case(tmp_path, slice_axis=0)
    answer = tmp_path / "poses.json"
    answer.write_text(json.dumps(case["answer"]))
    odd = tmp_path / "ax(1).nii.gz"
    odd.write_bytes(case["stack"].read_bytes())
    out = tmp_path / "mc"
    r = CliRunner().invoke(cli.app, ["export", str(answer), str(case["stack"]), "--to", "niftymic", "--out-dir", str(out),
                                     "--mask", str(case["mask"])], env={"COLUMNS": "400"})
    assert r.exit_code == 0, r.output
    assert f"--filenames {out / 'stacks' / 'ax.nii.gz'} --filenames-masks {out / 'masks' / 'ax_mask.nii.gz'} " in r.stdout
    assert "written again" in r.stderr and "rename" not in r.stderr
    assert "ATLAS_VOLUME.nii.gz: an atlas volume of the fetus's age" in r.stdout     # what to put in the command
    r = CliRunner().invoke(cli.app, ["export", str(answer), str(odd), "--to", "niftymic", "--out-dir",
                                     str(tmp_path / "mc2")], env={"COLUMNS": "400"})
    assert r.exit_code == 0, r.output
    assert "rename ax(1).nii.gz" in r.stderr


def test_niftymic_gets_each_file_it_needs_and_no_file_overwrites_another(tmp_path: Path) -> None:
    """A mask of its stack's name (stacks/ax.nii.gz, masks/ax_mask.nii.gz) rewritten beside its stack
    overwrites neither; a stack without an accepted slice is still placed (NAME.tfm from its slices
    with brain, no slice files); two stacks of one name, and a mask off its stack's grid, are refused
    by name."""
    case = make_case(tmp_path, slice_axis=0)
    (tmp_path / "masks").mkdir()
    mask = (tmp_path / "masks" / "ax.nii.gz")
    mask.write_bytes(case["mask"].read_bytes())
    out = tmp_path / "mc"
    done = export(case["answer"], [case["stack"]], [mask], out, "niftymic")
    assert done.stacks == [out / "stacks" / "ax.nii.gz"] and done.masks == [out / "masks" / "ax_mask.nii.gz"]
    np.testing.assert_array_equal(np.asarray(nib.load(done.stacks[0]).dataobj),
                                  np.transpose(case["data"], (1, 2, 0)))
    assert set(np.unique(np.asarray(nib.load(done.masks[0]).dataobj))) <= {0, 1}
    none = json.loads(json.dumps(case["answer"]))
    for item in none["stacks"][0]["slices"]:
        item["accepted"] = False
    bare = tmp_path / "none"
    assert export(none, [case["stack"]], None, bare, "niftymic").count == 0
    assert sorted(p.name for p in bare.glob("*.tfm")) == ["ax.tfm"]
    twice = json.loads(json.dumps(case["answer"]))
    twice["stacks"].append({**twice["stacks"][0], "index": 1})
    (tmp_path / "other").mkdir()
    copy = tmp_path / "other" / "ax.nii.gz"
    copy.write_bytes(case["stack"].read_bytes())
    with pytest.raises(UnusableInput, match="two stacks are named 'ax' and 'ax'"):
        export(twice, [case["stack"], copy], None, tmp_path / "x", "niftymic")
    upper = tmp_path / "other" / "AX.nii.gz"                          # one file on a case-insensitive disk
    copy.rename(upper)
    with pytest.raises(UnusableInput, match="named 'ax' and 'AX' \\(alike but for case\\)"):
        export(twice, [case["stack"], upper], None, tmp_path / "x", "niftymic")
    assert not (tmp_path / "x").exists()
    small = tmp_path / "small.nii.gz"
    nib.save(nib.Nifti1Image(np.ones((3, 3, 3), np.uint8), np.eye(4)), small)
    with pytest.raises(UnusableInput, match="small.nii.gz is not on its stack's grid"):
        export(case["answer"], [case["stack"]], [small], tmp_path / "y", "nesvor")


def _nesvor_world(path: Path, u: int, v: int) -> np.ndarray:
    """Where NeSVoR puts pixel ``(u, v)`` of the slice file ``path`` (``load_slices`` and
    ``affine2transformation`` of nesvor.image): voxel sizes from ``pixdim``, the rotation
    ``affine[:3, :3] / pixdim``, the pixel's offset from the slice's centre (its columns flipped where
    the rotation is improper), and the affine's translation moved to the centre."""
    image = nib.load(path)
    res = np.asarray(image.header["pixdim"][1:4], np.float64)
    affine = image.affine
    w, h = image.shape[:2]
    rotation = affine[:3, :3] @ np.diag(1 / res)
    centre = np.array([(w - 1) / 2 * res[0], (h - 1) / 2 * res[1], 0.0])
    shift = np.linalg.inv(rotation) @ affine[:3, 3] + centre
    offset = np.array([u * res[0], v * res[1], 0.0]) - centre
    if np.linalg.det(rotation) < 0:
        flip = np.diag([-1.0, 1.0, 1.0])
        rotation, shift, offset = rotation @ flip, flip @ shift, flip @ offset
    assert np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-5)      # NeSVoR takes it for a rotation
    return rotation @ (offset + shift)


@pytest.mark.parametrize("slice_axis", [2, 1])
def test_nesvor_reads_each_slice_file_at_its_atlas_place(slice_axis: int, tmp_path: Path) -> None:
    """NeSVoR places a slice by its rotation ``affine / pixdim`` about the slice's centre, not by the
    affine alone: each pixel lands at the atlas point its pose gives, the slice's third voxel size is
    the thickness, and the mask of ``{i}.nii.gz`` is ``mask_{i}.nii.gz``."""
    case = make_case(tmp_path, slice_axis)
    out = tmp_path / "nesvor"
    export(case["answer"], [case["stack"]], [case["mask"]], out, "nesvor", thickness_mm=[4.0])
    names = sorted(p.name for p in out.iterdir() if p.name.endswith((".nii", ".nii.gz")))
    slices = [n for n in names if not n.startswith("mask_")]
    assert names == sorted(slices + [f"mask_{n}" for n in slices]) and all(re.fullmatch(r"\d+\.nii\.gz", n) for n in slices)
    for i, k in enumerate([1, 2, 4, 5]):
        path = out / f"{i}.nii.gz"
        assert float(nib.load(path).header["pixdim"][3]) == pytest.approx(4.0, abs=1e-5)
        for u, v in ((0, 0), (15, 0), (7, 11)):
            want = case["poses"][k] @ np.array(voxel(slice_axis, (u, v), k) + [1.0])
            np.testing.assert_allclose(_nesvor_world(path, u, v), want[:3], atol=1e-4)


def _itk_matrix(transform) -> np.ndarray:
    """A SimpleITK affine transform as a ``4 x 4`` matrix: ``x -> A (x - c) + c + t``."""
    import SimpleITK as sitk

    t = sitk.AffineTransform(transform)
    a, c = np.array(t.GetMatrix()).reshape(3, 3), np.array(t.GetCenter())
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = a, c + np.array(t.GetTranslation()) - a @ c
    return out


def _niftymic_slices(stack: Path, name: str, folder: Path) -> dict[int, np.ndarray]:
    """Each slice NiftyMIC keeps of the file ``stack`` (named ``name`` by NiftyMIC) with its placement
    after reading ``--dir-input-mc folder`` (MotionUpdater.run of niftymic.utilities): the stack moved
    by ``name.tfm``; slice ``k`` by ``name_slice{k}.tfm`` composed with the stack's move undone; a
    slice without a file left out. Placements are slice voxel -> LPS mm."""
    import SimpleITK as sitk

    image = sitk.ReadImage(str(stack), sitk.sitkFloat64)
    whole = folder / f"{name}.tfm"
    moved = _itk_matrix(sitk.ReadTransform(str(whole))) if whole.is_file() else np.eye(4)
    pattern = re.compile(name + "_slice([0-9]+)[.]tfm")
    files = {int(m.group(1)): folder / m.group(0) for f in sorted(p.name for p in folder.iterdir()) if (m := pattern.match(f))}
    kept = {}
    for k in range(image.GetSize()[2]):
        piece = image[:, :, k:k + 1]
        placed = np.eye(4)
        placed[:3, :3] = np.array(piece.GetDirection()).reshape(3, 3) @ np.diag(piece.GetSpacing())
        placed[:3, 3] = piece.GetOrigin()
        if k in files:
            own = _itk_matrix(sitk.ReadTransform(str(files[k])))
            kept[k] = own @ np.linalg.inv(moved) @ moved @ placed
    return kept


@pytest.mark.parametrize("slice_axis", [2, 0])
def test_niftymic_finds_and_applies_each_slices_transform_by_its_own_rules(slice_axis: int, tmp_path: Path) -> None:
    """NiftyMIC names a stack by its file name without every match of the pattern ``.nii`` (a file
    ``haste_nii.nii`` is the stack ``haste``), finds its transforms by that name, and keeps only the
    slices that have one: each slice it keeps lies where its pose puts it, in LPS."""
    sitk = pytest.importorskip("SimpleITK")
    case = make_case(tmp_path, slice_axis)
    stack = tmp_path / "haste_nii.nii"
    nib.save(nib.load(case["stack"]), stack)
    answer = json.loads(json.dumps(case["answer"]))
    answer["stacks"][0]["filename"] = stack.name
    out = tmp_path / "mc"
    done = export(answer, [stack], None, out, "niftymic")
    assert sitk.ReadImage(str(done.stacks[0])).GetSize() == (20, 16, 6)
    kept = _niftymic_slices(done.stacks[0], "haste", out)
    assert sorted(kept) == [1, 2, 4, 5]
    for k, placed in kept.items():
        for u, v in ((0, 0), (19, 15), (5, 9)):
            want = F @ case["poses"][k] @ np.array(voxel(slice_axis, (u, v), k) + [1.0])
            np.testing.assert_allclose((placed @ [u, v, 0, 1.0])[:3], want[:3], atol=1e-4)
    with pytest.raises(UnusableInput, match="NiftyMIC reads stacks named"):
        export(answer, [case["stack"].rename(tmp_path / "AX.NII.GZ")], None, tmp_path / "upper", "niftymic")


def test_niftymic_is_given_masks_it_takes_as_they_are_meant(case: dict, tmp_path: Path) -> None:
    """NiftyMIC lays a mask's stored voxels on its stack's and refuses values above 1: a mask of 0 and
    255, and one stored with an axis reversed, are written again as 0 and 1 on the stack's voxels,
    named by their stacks (two masks of one name do not overwrite each other); a 0/1 mask stored as
    its stack is given as it is."""
    sitk = pytest.importorskip("SimpleITK")
    flip = np.diag([1.0, -1.0, 1.0, 1.0])
    flip[1, 3] = SHAPE[1] - 1
    stored = {"a/mask.nii.gz": (case["mask_data"] * 255, case["scanner_from_voxel"]),
              "b/mask.nii.gz": (case["mask_data"][:, ::-1, :], case["scanner_from_voxel"] @ flip),
              "c/mask.nii.gz": (case["mask_data"], case["scanner_from_voxel"])}
    stacks, masks = [], []
    answer = {"stacks": []}
    for s, (name, (values, affine)) in enumerate(stored.items()):
        path = tmp_path / name
        path.parent.mkdir()
        nib.save(nib.Nifti1Image(np.ascontiguousarray(values).astype(np.uint8), affine), path)
        stacks.append(tmp_path / f"{'abc'[s]}x.nii.gz")
        stacks[-1].write_bytes(case["stack"].read_bytes())
        masks.append(path)
        answer["stacks"].append({**case["answer"]["stacks"][0], "index": s, "filename": stacks[-1].name})
    out = tmp_path / "mc"
    done = export(answer, stacks, masks, out, "niftymic")
    assert done.masks == [out / "masks" / "ax_mask.nii.gz", out / "masks" / "bx_mask.nii.gz", masks[2]]
    for path in done.masks:
        image = sitk.ReadImage(str(path), sitk.sitkUInt8)
        assert image.GetSize() == sitk.ReadImage(str(stacks[0])).GetSize()
        np.testing.assert_array_equal(sitk.GetArrayFromImage(image), np.transpose(case["mask_data"], (2, 1, 0)))


def test_niftymic_is_given_files_compressed_as_their_names_say(case: dict, tmp_path: Path) -> None:
    """ITK reads a file by its name's compression: a gzipped stack named ``.nii`` and a plain mask named
    ``.nii.gz`` (both read here by their content, as the server reads them) are written again as their
    names say, the same voxels; the mask failed to read, leaving a half-written folder."""
    sitk = pytest.importorskip("SimpleITK")
    stack, mask = tmp_path / "in" / "ax.nii", tmp_path / "in" / "ax_mask.nii.gz"
    stack.parent.mkdir()
    stack.write_bytes(case["stack"].read_bytes())                                    # gzipped, named .nii
    plain = nib.Nifti1Image(case["mask_data"], case["scanner_from_voxel"])
    mask.write_bytes(plain.to_bytes())                                               # plain, named .nii.gz
    answer = {"stacks": [{**case["answer"]["stacks"][0], "filename": stack.name}]}
    out = tmp_path / "mc"
    done = export(answer, [stack], [mask], out, "niftymic")
    assert done.stacks == [out / "stacks" / "ax.nii"] and done.masks == [out / "masks" / "ax_mask.nii.gz"]
    np.testing.assert_array_equal(sitk.GetArrayFromImage(sitk.ReadImage(str(done.stacks[0]))),
                                  np.transpose(case["data"], (2, 1, 0)))
    np.testing.assert_array_equal(sitk.GetArrayFromImage(sitk.ReadImage(str(done.masks[0]), sitk.sitkUInt8)),
                                  np.transpose(case["mask_data"], (2, 1, 0)))


@pytest.mark.parametrize("foreign", ["T2_ax.nii.gz", "7.nii", "mask_3.nii", "ax.tfm"])
def test_an_overwrite_refuses_any_file_of_the_folder_a_tool_would_read(foreign: str, case: dict, tmp_path: Path) -> None:
    """NeSVoR reads every ``*.nii`` and ``*.nii.gz`` of its folder (a name not a number stops it) and
    NiftyMIC every ``NAME.tfm``: such a file that no export wrote is refused even with ``overwrite``;
    files in subfolders, which neither tool reads, are not."""
    out = tmp_path / "out"
    export(case["answer"], [case["stack"]], None, out, "nesvor")
    (out / "stacks").mkdir()
    (out / "stacks" / "0.nii.gz").write_bytes(b"the user's own")
    assert export(case["answer"], [case["stack"]], None, out, "nesvor", overwrite=True).count == 4
    (out / foreign).write_bytes(b"the user's own")
    with pytest.raises(ArgumentError, match=f"holds {re.escape(foreign)}, a file a tool would read"):
        export(case["answer"], [case["stack"]], None, out, "nesvor", overwrite=True)


def test_an_overwrite_removes_nothing_outside_its_folder_whatever_the_manifest_names(tmp_path: Path) -> None:
    """A manifest copied, shared or edited may name an absolute path, a path through ``..`` or through
    a linked subfolder: ``overwrite`` removes none of them, only the files inside the folder it lists
    (an absolute name deleted the file it named anywhere on the disk)."""
    from client.export_folder import MANIFEST, clear_for_export

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    victims = [elsewhere / n for n in ("absolute.txt", "dotdot.txt", "linked.txt")]
    for v in victims:
        v.write_text("the user's own")
    out = tmp_path / "out"
    out.mkdir()
    (out / "sub").symlink_to(elsewhere, target_is_directory=True)
    (out / "0.nii.gz").write_bytes(b"an earlier export's")
    (out / MANIFEST).write_text(json.dumps([str(victims[0]), "../elsewhere/dotdot.txt", "sub/linked.txt", "0.nii.gz"]))
    clear_for_export(out, overwrite=True)
    assert all(v.read_text() == "the user's own" for v in victims)
    assert not (out / "0.nii.gz").exists()


def test_the_cli_gives_niftymic_the_thickness(case: dict, tmp_path: Path) -> None:
    """``--thickness`` reaches NiftyMIC as ``--slice-thicknesses``, one per stack."""
    answer = tmp_path / "poses.json"
    answer.write_text(json.dumps(case["answer"]))
    r = CliRunner().invoke(cli.app, ["export", str(answer), str(case["stack"]), "--to", "niftymic", "--out-dir",
                                     str(tmp_path / "mc"), "--thickness", "2.5"], env={"COLUMNS": "400"})
    assert r.exit_code == 0, r.output
    assert f"--filenames {case['stack']} --slice-thicknesses 2.5 --dir-input-mc" in r.stdout


def test_a_file_that_does_not_read_leaves_the_folder_untouched_and_an_answer_without_trusted_slices_says_so(
        case: dict, tmp_path: Path) -> None:
    """Every stack and mask file is read before anything is written: a truncated mask (or stack)
    refuses the export with the folder as it was, so that the export run again with the right files
    writes into it; an answer with no slice to write exits 12 and points at ``--all-slices``."""
    answer = tmp_path / "poses.json"
    answer.write_text(json.dumps(case["answer"]))
    out = tmp_path / "slices"
    truncated = tmp_path / "cut" / case["mask"].name
    truncated.parent.mkdir()
    truncated.write_bytes(case["mask"].read_bytes()[:60])
    run = lambda *more: CliRunner().invoke(  # noqa: E731
        cli.app, ["export", str(answer), str(case["stack"]), "--to", "nesvor", "--out-dir", str(out), *more],
        env={"COLUMNS": "200"})
    for bad in (truncated, tmp_path / "cut" / "ax.nii.gz"):
        if bad.name == "ax.nii.gz":
            bad.write_bytes(case["stack"].read_bytes()[:400])
            r = CliRunner().invoke(cli.app, ["export", str(answer), str(bad), "--to", "nesvor", "--out-dir", str(out)],
                                   env={"COLUMNS": "200"})
        else:
            r = run("--mask", str(bad))
        assert r.exit_code == 5 and bad.name in r.output, r.output
        assert not out.exists() or not list(out.iterdir())
    assert run("--mask", str(case["mask"])).exit_code == 0 and len(list(out.glob("mask_*.nii.gz"))) == 4
    refused = {**case["answer"], "stacks": [{**st, "slices": [{**sl, "accepted": False} for sl in st["slices"]]}
                                            for st in case["answer"]["stacks"]]}
    answer.write_text(json.dumps(refused))
    r = run("--overwrite")
    assert r.exit_code == 12 and "wrote 0 slices" in r.stdout and "--all-slices" in r.stderr and "next:" not in r.stdout
    assert run("--overwrite", "--all-slices").exit_code == 0


def test_a_folder_given_with_a_tilde_is_written_where_the_user_means(case: dict, tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """The folder checked and made was the expanded one, the files written under a literal ``~``."""
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "home").mkdir()
    done = export(case["answer"], [case["stack"]], None, Path("~/exp"), "nesvor")
    assert done.count == 4 and len(list((tmp_path / "home" / "exp").glob("*.nii.gz"))) == 4
    assert not (tmp_path / "~").exists()


def test_a_probability_map_mask_marks_the_voxels_the_server_takes_for_brain(case: dict, tmp_path: Path) -> None:
    """A mask of fractions (a probability map: brain 0.9, elsewhere 0.02) marks the voxels at half its
    largest value or more, as the server reads it, in NeSVoR's slice masks and NiftyMIC's 0/1 copy."""
    sitk = pytest.importorskip("SimpleITK")
    soft = tmp_path / "soft" / "ax_mask.nii.gz"
    soft.parent.mkdir()
    nib.save(nib.Nifti1Image(np.where(case["mask_data"] > 0, 0.9, 0.02).astype(np.float32),
                             case["scanner_from_voxel"]), soft)
    out = tmp_path / "n"
    export(case["answer"], [case["stack"]], [soft], out, "nesvor")
    for i, k in enumerate((1, 2, 4, 5)):
        np.testing.assert_array_equal(np.asarray(nib.load(out / f"mask_{i}.nii.gz").dataobj)[:, :, 0],
                                      case["mask_data"][:, :, k])
    done = export(case["answer"], [case["stack"]], [soft], tmp_path / "mc", "niftymic")
    np.testing.assert_array_equal(sitk.GetArrayFromImage(sitk.ReadImage(str(done.masks[0]), sitk.sitkUInt8)),
                                  np.transpose(case["mask_data"], (2, 1, 0)))


def test_the_command_printed_next_reads_as_the_paths_in_a_shell(case: dict, tmp_path: Path) -> None:
    """Paths with spaces come quoted in the command printed to paste into a shell."""
    import shlex

    answer = tmp_path / "poses.json"
    answer.write_text(json.dumps(case["answer"]))
    out = tmp_path / "my scans" / "out nm"
    r = CliRunner().invoke(cli.app, ["export", str(answer), str(case["stack"]), "--to", "niftymic", "--out-dir", str(out),
                                     "--mask", str(case["mask"])], env={"COLUMNS": "400"})
    assert r.exit_code == 0, r.output
    words = shlex.split(next(line for line in r.stdout.splitlines() if line.startswith("next: "))[len("next: "):])
    assert words[words.index("--dir-input-mc") + 1] == str(out)
    assert words[words.index("--filenames") + 1] == str(case["stack"])
