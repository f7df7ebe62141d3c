"""``POST /v1/masks`` and the ``localisation`` of ``/v1/predict``: a generated whole-uterus stack in,
a mask on its own grid out; bad input gets a 4xx that names it."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage
from fastapi.testclient import TestClient

from model_export.localiser.scenes import HeadModel, synth_stack
from service.io.volume import Volume, read_volume, write_volume
from tests.support.phantoms import phantom_brain


@pytest.fixture(scope="module")
def uterus_files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, np.ndarray]:
    """A generated whole-uterus stack (phantom brain, held-out surroundings), its true mask file and mask."""
    image, mask, affine = phantom_brain(11)
    volume, truth = synth_stack(HeadModel.from_arrays(image, mask, affine), np.random.default_rng(100), "heldout")
    rotated = volume.affine.copy()
    rotated[:3, :3] = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]]) @ volume.affine[:3, :3]   # an oblique-free but
    rotated[:3, 3] = (-80.0, 12.0, 40.0)                                                      # non-axial stack
    d = tmp_path_factory.mktemp("uterus")
    write_volume(Volume(volume.array, rotated), d / "uterus.nii.gz")
    write_volume(Volume(truth.astype(np.uint8), rotated), d / "uterus_mask.nii.gz")
    return d / "uterus.nii.gz", d / "uterus_mask.nii.gz", truth


def post_masks(client: TestClient, *paths: Path, **data: str):  # noqa: ANN201
    files = [("stacks", (p.name, p.read_bytes())) for p in paths]
    return client.post("/v1/masks", files=files, data=data)


def test_masks_come_back_on_each_stacks_grid_with_a_report(real_client: TestClient, uterus_files, tmp_path: Path) -> None:
    stack, _, truth = uterus_files
    r = post_masks(real_client, stack, stack)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "application/zip"
    archive = zipfile.ZipFile(io.BytesIO(r.content))
    assert sorted(archive.namelist()) == ["report.json", "uterus-1_mask.nii.gz", "uterus_mask.nii.gz"]
    report = json.loads(archive.read("report.json"))
    assert isinstance(report, list) and len(report) == 2               # api-v1: an object per stack
    row = report[0]
    assert set(row) >= {"filename", "brain_volume_ml", "confidence", "slices_with_brain", "localiser"}
    assert row["filename"] == "uterus.nii.gz" and row["confidence"] > 0.5
    (tmp_path / "m.nii.gz").write_bytes(archive.read("uterus_mask.nii.gz"))
    mask, original = read_volume(tmp_path / "m.nii.gz"), read_volume(stack)
    assert mask.array.shape == original.array.shape and np.allclose(mask.affine, original.affine, atol=1e-4)
    assert set(np.unique(mask.array)) <= {0, 1}
    found = mask.array > 0
    assert 2 * (found & truth).sum() / (found.sum() + truth.sum()) > 0.8
    assert row["slices_with_brain"] == int(found.any(axis=(0, 1)).sum())


def test_a_margin_grows_each_mask_by_that_distance_on_its_grid(real_client: TestClient, uterus_files,
                                                                tmp_path: Path) -> None:
    stack = uterus_files[0]
    masks = {}
    for margin in ("0", "3"):
        r = post_masks(real_client, stack, margin_mm=margin)
        assert r.status_code == 200, r.text
        archive = zipfile.ZipFile(io.BytesIO(r.content))
        (tmp_path / "m.nii.gz").write_bytes(archive.read("uterus_mask.nii.gz"))
        masks[margin] = (read_volume(tmp_path / "m.nii.gz").array > 0, json.loads(archive.read("report.json")))
    (plain, plain_report), (wide, wide_report) = masks["0"], masks["3"]
    spacing = read_volume(stack).spacing
    outside = ndimage.distance_transform_edt(~plain, sampling=spacing)
    assert np.array_equal(wide, outside <= 3.0) and wide.sum() > 1.2 * plain.sum()
    assert wide_report[0]["margin_mm"] == 3.0 and plain_report[0]["margin_mm"] == 0.0
    assert wide_report[0]["brain_volume_ml"] > plain_report[0]["brain_volume_ml"]
    for bad in ("-1", "21", "nan", "wide"):
        r = post_masks(real_client, stack, margin_mm=bad)
        assert r.status_code in (400, 422) and "margin_mm" in r.text, (bad, r.text)


def test_masks_refuse_what_they_cannot_use(real_client: TestClient, uterus_files, tmp_path: Path) -> None:
    stack = uterus_files[0]
    r = post_masks(real_client, stack, model="nope")
    assert r.status_code == 404 and "localiser 'nope'" in r.json()["detail"]
    junk = tmp_path / "notes.txt"
    junk.write_text("not an image")
    r = post_masks(real_client, junk)
    assert r.status_code == 415 and "notes.txt" in r.json()["detail"]
    r = real_client.post("/v1/masks", files=[("stacks", (stack.name, stack.read_bytes()))], data={"mc_samples": "3"})
    assert r.status_code == 400 and "mc_samples" in r.json()["detail"]
    wide = tmp_path / "wide.nii.gz"               # small bytes over a field of view of 900 mm: the search bounded
    write_volume(Volume(np.zeros((100, 100, 99), np.float32), np.diag([9.0, 9.0, 10.0, 1.0])), wide)
    r = post_masks(real_client, wide, wide, wide, wide)
    assert r.status_code == 413 and "the localiser would search" in r.json()["detail"], r.text
    binary = tmp_path / "stack_mask.nii.gz"       # a mask sent as a stack
    write_volume(Volume((np.arange(20 * 20 * 6).reshape(20, 20, 6) % 7 == 0).astype(np.uint8), np.eye(4)), binary)
    r = post_masks(real_client, stack, binary)
    assert r.status_code == 422 and "stack_mask.nii.gz holds the values 0 and 1 alone" in r.json()["detail"], r.text


def test_predict_says_how_each_stack_was_localised(real_client: TestClient, uterus_files) -> None:
    stack, mask, _ = uterus_files
    files = [("stacks", (stack.name, stack.read_bytes()))]
    without = real_client.post("/v1/predict", files=files, data={"mc_samples": "2"})
    assert without.status_code == 200, without.text
    where = without.json()["stacks"][0]["localisation"]
    assert where["method"] == "network" and where["confidence"] > 0.5 and 50 < where["brain_volume_ml"] < 700
    reasons = [s["reason"] for s in without.json()["stacks"][0]["slices"]]
    assert 0 < reasons.count("empty") < len(reasons)              # slices beyond the head are empty, not all
    assert where["pose_mask_inset_mm"] == 2.0                        # the localiser's mask holds the CSF
    made_by = without.json()["localiser"]                             # which localiser found it
    assert made_by["name"] == "default" and made_by["version"] and len(made_by["sha256"]) == 64
    files.append(("masks", (mask.name, mask.read_bytes())))
    with_mask = real_client.post("/v1/predict", files=files, data={"mc_samples": "2"})
    assert with_mask.json()["localiser"] is None
    assert with_mask.json()["stacks"][0]["localisation"] == {**with_mask.json()["stacks"][0]["localisation"],
                                                             "method": "mask", "pose_mask_inset_mm": 0.0}
    said = real_client.post("/v1/predict", files=files, data={"mc_samples": "2", "masks_hold_csf": "true"})
    assert said.status_code == 200, said.text
    assert said.json()["stacks"][0]["localisation"]["pose_mask_inset_mm"] == 2.0
    bad = real_client.post("/v1/predict", files=files, data={"masks_hold_csf": "perhaps"})
    assert bad.status_code in (400, 422) and "masks_hold_csf" in bad.text


def test_a_stack_of_noise_answers_200_with_empty_slices(real_client: TestClient, tmp_path: Path) -> None:
    noise = np.random.default_rng(1).random((200, 200, 12), np.float32) * 300
    write_volume(Volume(noise, np.diag([1.5, 1.5, 3.0, 1.0])), tmp_path / "noise.nii.gz")
    r = real_client.post("/v1/predict", files=[("stacks", ("noise.nii.gz", (tmp_path / "noise.nii.gz").read_bytes()))],
                         data={"mc_samples": "2"})
    assert r.status_code == 200, r.text
    stack = r.json()["stacks"][0]
    assert stack["localisation"]["confidence"] < 0.3
    if stack["localisation"]["confidence"] < 0.15:               # below MIN_CONFIDENCE: no brain at all
        assert all(s["reason"] == "empty" for s in stack["slices"]) and stack["localisation"]["brain_volume_ml"] == 0


def test_masks_of_a_nifti_upload_carry_its_transforms(real_client: TestClient, uterus_files, tmp_path: Path) -> None:
    """A NIfTI whose sform (code 2) and qform disagree: the mask has the upload's two transforms and
    codes, so that it overlays the stack in a viewer of either rule."""
    nib = pytest.importorskip("nibabel")
    source = nib.load(str(uterus_files[0]))
    qform = source.affine.copy()
    qform[:3, 3] += (12.0, 0.0, 0.0)
    source.header.set_qform(qform, code=1)
    source.header.set_sform(source.affine, code=2)
    path = tmp_path / "sq.nii.gz"
    nib.save(nib.Nifti1Image(np.asarray(source.dataobj), None, source.header), str(path))
    r = post_masks(real_client, path)
    assert r.status_code == 200, r.text
    (tmp_path / "m.nii.gz").write_bytes(zipfile.ZipFile(io.BytesIO(r.content)).read("sq_mask.nii.gz"))
    mask, stack = nib.load(str(tmp_path / "m.nii.gz")), nib.load(str(path))
    assert mask.shape == stack.shape
    for get in ("get_best_affine", "get_qform", "get_sform"):
        np.testing.assert_allclose(getattr(mask.header, get)(), getattr(stack.header, get)(), atol=1e-4)
    assert (int(mask.header["sform_code"]), int(mask.header["qform_code"])) == (2, 1)


def test_a_nearly_square_grid_and_a_long_file_name_get_their_mask(real_client: TestClient, uterus_files,
                                                                    tmp_path: Path) -> None:
    """A stack whose sform axes lie 0.03 deg off right angles (within what a file may hold) gets its
    mask with its own sform, where writing it failed (a 500); a file name of 255 characters gets a
    mask named within 255, and nothing on disk is named after it."""
    nib = pytest.importorskip("nibabel")
    source = nib.load(str(uterus_files[0]))
    sheared = source.affine.copy()
    sheared[:3, 1] += 5e-4 * np.linalg.norm(sheared[:3, 1]) * sheared[:3, 0] / np.linalg.norm(sheared[:3, 0])
    source.header.set_sform(sheared, code=2)
    name = "Doe_Jane_19800101_" + "x" * (255 - 18 - 7) + ".nii.gz"
    path = tmp_path / name
    nib.save(nib.Nifti1Image(np.asarray(source.dataobj), None, source.header), str(path))
    r = post_masks(real_client, path)
    assert r.status_code == 200, r.text
    archive = zipfile.ZipFile(io.BytesIO(r.content))
    member = next(n for n in archive.namelist() if n != "report.json")
    assert member.startswith("Doe_Jane_") and member.endswith("_mask.nii.gz") and len(member) <= 255
    (tmp_path / "m.nii.gz").write_bytes(archive.read(member))
    np.testing.assert_allclose(nib.load(str(tmp_path / "m.nii.gz")).header.get_sform(), sheared, atol=1e-4)


def test_a_stack_whose_axes_are_a_hair_off_right_angles_gets_its_mask_on_its_grid(real_client: TestClient,
                                                                                     uterus_files, tmp_path: Path) -> None:
    """An MHA stack whose axes lie 0.05 deg off right angles (within the service's tolerance; ITK
    stores them as the nearest rotation): its mask's sform is the stack's own placement, to float32's
    precision, and the mask is taken back with its stack (it was 0.2 mm off the grid, and refused)."""
    from service.io.readers import read_upload

    stack, _, _ = uterus_files
    volume = read_volume(stack)
    leaning = volume.affine.copy()
    leaning[:3, 1] += 9e-4 * np.linalg.norm(leaning[:3, 1]) * leaning[:3, 0] / np.linalg.norm(leaning[:3, 0])
    spacing = np.linalg.norm(leaning[:3, :3], axis=0)
    lps = np.diag([-1.0, -1.0, 1.0])
    numbers = lambda values: " ".join(str(float(v)) for v in values)  # noqa: E731
    header = (f"ObjectType = Image\nNDims = 3\nDimSize = {' '.join(map(str, volume.array.shape))}\n"
              f"ElementType = MET_FLOAT\nElementSpacing = {numbers(spacing)}\n"
              f"TransformMatrix = {numbers((lps @ leaning[:3, :3] / spacing).T.ravel())}\n"
              f"Offset = {numbers(lps @ leaning[:3, 3])}\nElementDataFile = LOCAL\n")
    upload = tmp_path / "leaning.mha"
    upload.write_bytes(header.encode() + np.asfortranarray(volume.array.astype(np.float32)).tobytes(order="F"))
    read = read_upload(upload, "leaning.mha")
    assert np.allclose(read.affine, leaning, atol=1e-4)                 # the file places it so
    r = post_masks(real_client, upload)
    assert r.status_code == 200, r.text
    (tmp_path / "m.nii.gz").write_bytes(zipfile.ZipFile(io.BytesIO(r.content)).read("leaning_mask.nii.gz"))
    mask = read_upload(tmp_path / "m.nii.gz", "m.nii.gz", magnitudes=False)
    assert np.abs(mask.affine - read.affine).max() < 1e-4
    files = [("stacks", (upload.name, upload.read_bytes())),
             ("masks", ("m.nii.gz", (tmp_path / "m.nii.gz").read_bytes()))]
    answer = real_client.post("/v1/predict", files=files, data={"mc_samples": "2", "bias_correction": "false"})
    assert answer.status_code == 200, answer.text


def test_a_region_drawn_around_the_head_is_searched_not_taken_for_the_brain(real_client: TestClient, uterus_files,
                                                                           tmp_path: Path) -> None:
    """A box around the head sent as the stack's mask (api-v1: a region of interest) is where the
    localiser finds the brain, not the brain itself: the answer is the one without a mask, and says
    so; a box that holds no brain gives empty slices."""
    from service.preprocess.localisation import is_region_of_interest

    stack, _, truth = uterus_files
    volume = read_volume(stack)
    ends = [np.flatnonzero(truth.any(axis=tuple(a for a in range(3) if a != k)))[[0, -1]] for k in range(3)]
    box = np.zeros(truth.shape, np.uint8)
    box[tuple(slice(max(lo - 12, 0), hi + 13) for lo, hi in ends)] = 1
    far = np.zeros(truth.shape, np.uint8)
    far[tuple(slice(0, max(lo - 2, 1)) if k < 2 else slice(None) for k, (lo, _) in enumerate(ends))] = 1
    assert is_region_of_interest(box > 0, volume.spacing) and not (far.astype(bool) & truth).any()

    def answer(mask: np.ndarray | None) -> dict:
        files = [("stacks", (stack.name, stack.read_bytes()))]
        if mask is not None:
            write_volume(Volume(mask, volume.affine), tmp_path / "roi.nii.gz")
            files.append(("masks", ("roi.nii.gz", (tmp_path / "roi.nii.gz").read_bytes())))
        r = real_client.post("/v1/predict", files=files, data={"mc_samples": "2"})
        assert r.status_code == 200, r.text
        return r.json()

    without, boxed = answer(None), answer(box)
    found = boxed["stacks"][0]["localisation"]
    assert found["method"] == "network" and found["region_of_interest"] is True and boxed["localiser"] is not None
    assert found["brain_volume_ml"] == without["stacks"][0]["localisation"]["brain_volume_ml"]
    assert [s["reason"] == "empty" for s in boxed["stacks"][0]["slices"]] == \
        [s["reason"] == "empty" for s in without["stacks"][0]["slices"]]
    assert is_region_of_interest(far > 0, volume.spacing)
    nowhere = answer(far)["stacks"][0]
    assert nowhere["localisation"]["brain_volume_ml"] == 0 and nowhere["localisation"]["confidence"] == 0
    assert all(s["reason"] == "empty" for s in nowhere["slices"])


def test_a_region_without_a_localiser_to_search_it_is_refused_on_both_routes(oracle, uterus_files,
                                                                           tmp_path: Path) -> None:  # noqa: ANN001
    """A server with no localiser named default answers a box around the head with a 400 naming
    ``masks``, on ``/v1/predict`` and on a job's submission alike (which leaves no job)."""
    from service.inference.registry import ModelRegistry
    from tests.api.conftest import make_client

    stack, _, truth = uterus_files
    volume = read_volume(stack)
    ends = [np.flatnonzero(truth.any(axis=tuple(a for a in range(3) if a != k)))[[0, -1]] for k in range(3)]
    box = np.zeros(truth.shape, np.uint8)
    box[tuple(slice(max(lo - 12, 0), hi + 13) for lo, hi in ends)] = 1
    write_volume(Volume(box, volume.affine), tmp_path / "roi.nii.gz")
    files = [("stacks", (stack.name, stack.read_bytes())), ("masks", ("roi.nii.gz", (tmp_path / "roi.nii.gz").read_bytes()))]
    (tmp_path / "no_localisers").mkdir()
    with make_client(ModelRegistry({"default": oracle}), localisers_dir=tmp_path / "no_localisers",
                     data_dir=tmp_path / "data") as client:
        for route in ("/v1/predict", "/v1/reconstructions"):
            r = client.post(route, files=files, data={"mc_samples": "2"})
            assert r.status_code == 400 and "box around the head" in r.json()["detail"], (route, r.text)
        assert not any(client.app.state.job_store.counts().values())
    assert not [p for p in (tmp_path / "data").rglob("*") if p.is_file() and "inputs" in p.parts]
