"""Reconstruction jobs through the app, on both back-ends (embedded; Redis + RQ + ``svrnet-worker``):
lifecycle, results, stages, cancel, failure, 429 when the queue is full, a job queued across a
restart."""

from __future__ import annotations

import io
import json
import re
import time
import zipfile
from datetime import datetime, timedelta
from pathlib import Path

import anyio
import numpy as np
import pytest
import SimpleITK as sitk
from fastapi.testclient import TestClient

from service.api import deps, job_submission, reconstructions
from service.inference.registry import ModelRegistry
from service.io.volume import Volume, read_volume, write_volume
from service.jobs.sqlite_store import SqliteJobStore
from tests.api.conftest import OracleEstimator, make_client, tiny_model_path  # noqa: F401 - fixture
from tests.jobs.conftest import BACKENDS, env_of
from tests.support.live_server import Worker
from tests.support.local_client import LocalClient
from tests.support.phantoms import orthogonal_stacks_case

both = pytest.mark.parametrize("queue_settings", BACKENDS, indirect=True)


@pytest.fixture(scope="module")
def case(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Three small orthogonal stacks with their true poses as a /v1/predict body."""
    files, body = orthogonal_stacks_case(tmp_path_factory.mktemp("job_case"))
    return {"files": files, "poses": body}


def submit(client: TestClient, case: dict, poses: object = None, masks: list[bytes] | None = None,
           stacks: list[bytes] | None = None, headers: dict[str, str] | None = None, with_masks: bool = True,
           **data: str):  # noqa: ANN201
    """Submit the case; ``poses``: a body (default: the true poses) or the raw text of one; ``masks``
    and ``stacks``: the files' bytes (default: the case's; no masks at all without ``with_masks``)."""
    text = poses if isinstance(poses, str) else json.dumps(poses or case["poses"])
    stacks = stacks or [s.read_bytes() for s, _ in case["files"]]
    files = [("stacks", (s.name, data_)) for (s, _), data_ in zip(case["files"], stacks)]
    masks = masks or [m.read_bytes() for _, m in case["files"]]
    files += [("masks", (m.name, data_)) for (_, m), data_ in zip(case["files"], masks) if with_masks]
    files.append(("poses", ("poses.json", text.encode(), "application/json")))
    data = {"resolution_mm": "2.0", "svr_iterations": "1", "atlas_frame": "false", **data}   # a phantom, no brain
    return client.post("/v1/reconstructions", files=files, data=data, headers=headers)


def zeroed(case: dict, which: int) -> list[bytes]:
    """The case's stack (``which`` 0) or mask (1) files with every voxel 0."""
    out = []
    for files in case["files"]:
        image = read_volume(files[which])
        path = files[which].parent / f"zero_{files[which].name}"
        write_volume(Volume(np.zeros_like(image.array), image.affine), path)
        out.append(path.read_bytes())
    return out


def wait(client: TestClient, job_id: str, timeout: float = 180.0) -> dict:
    seen = set()
    t0 = time.time()
    while time.time() - t0 < timeout:
        st = client.get(f"/v1/reconstructions/{job_id}").json()
        seen.add(st["status"])
        if st["status"] in ("succeeded", "failed", "cancelled"):
            st["seen"] = seen
            return st
        time.sleep(0.3)
    raise AssertionError(f"job {job_id} did not finish in {timeout} s (seen {seen})")


@pytest.fixture
def client(queue_settings: dict[str, str], workers: list):  # noqa: ANN201
    """The app on the back-end of ``queue_settings`` (with a worker of its own for ``redis``)."""
    with make_client(ModelRegistry({"default": OracleEstimator()}), **queue_settings) as c:
        yield c


@both
def test_job_succeeds_with_volume_preview_and_report(client: TestClient, case: dict, tmp_path: Path) -> None:
    r = submit(client, case)
    assert r.status_code == 202, r.text
    job_id = r.json()["job_id"]
    assert r.headers["location"] == f"/v1/reconstructions/{job_id}" == r.json()["status_url"]
    early = client.get(f"/v1/reconstructions/{job_id}/volume")
    assert early.status_code in (409, 200)
    first = client.get(f"/v1/reconstructions/{job_id}").json()     # no end of its keeping before it ends
    assert first["expires_at"] is None or first["status"] == "succeeded", first
    st = wait(client, job_id)
    assert st["status"] == "succeeded", st
    kept = datetime.fromisoformat(st["expires_at"]) - datetime.fromisoformat(st["updated_at"])
    assert kept == timedelta(hours=client.app.state.settings.retention_hours), st   # when the stores expire it
    assert st["progress"] == 1.0 and st["result_url"].endswith("/volume") and st["preview_url"].endswith(".png")
    vol_bytes = client.get(st["result_url"]).content
    opened = []
    real_open = anyio.open_file
    with pytest.MonkeyPatch.context() as mp:                  # a client checks the download's size first
        mp.setattr(anyio, "open_file", lambda *a, **k: opened.append(a) or real_open(*a, **k))
        head = client.head(st["result_url"])
    assert opened == []                                       # ... and the server does not read the file for it
    assert head.status_code == 200 and head.content == b"" and int(head.headers["content-length"]) == len(vol_bytes)
    (tmp_path / "v.nii.gz").write_bytes(vol_bytes)
    vol = read_volume(tmp_path / "v.nii.gz")
    assert vol.array.ndim == 3 and np.isfinite(vol.array).all() and vol.array.max() > 0
    np.testing.assert_allclose(vol.spacing, 2.0, atol=1e-4)
    png = client.get(st["preview_url"])
    assert png.status_code == 200 and png.content[:8] == b"\x89PNG\r\n\x1a\n"
    report = st["report"]
    assert report and len(report["slices"]) == 36
    assert isinstance(st["coherent"], bool) and st["coherent"] == report["quality"]["coherent"]
    assert {"stack", "slice", "included", "exclusion_reason", "weight"} <= set(report["slices"][0])
    made_by = report["provenance"]                             # what made it, without the clients' file names
    assert made_by["masks"] == ["uploaded"] * 3 and made_by["localiser"] is None and made_by["service"]["version"]
    assert made_by["model"]["name"] == "default" and set(made_by["model"]) == {"name", "version", "backbone", "sha256"}
    assert made_by["model"]["sha256"] != case["poses"].get("model", {}).get("sha256")   # the job's own, not the upload's
    assert json.loads(client.get(st["poses_url"]).text)["model"] == made_by["model"]   # as RefinedPoses requires
    assert made_by["masks_hold_csf"] is False
    assert not any(f.name in json.dumps(made_by) for f, _ in case["files"])
    times = report["timings_s"]
    assert times["job"] >= times["all_paths"] >= times["total"] > 0     # the job holds its paths, they the winner
    assert client.get("/v1/reconstructions/unknown").status_code == 404
    long_id = client.get("/v1/reconstructions/" + "a" * 5000)               # not echoed whole
    assert long_id.status_code == 404 and "(5000 characters)" in long_id.json()["detail"]
    assert len(long_id.json()["detail"]) < 200
    # The refined poses, in the /v1/predict schema (a valid `poses` input to a new job).
    assert st["poses_url"] == f"/v1/reconstructions/{job_id}/poses"
    body = client.get(st["poses_url"]).json()
    slices = [s for stack in body["stacks"] for s in stack["slices"]]
    assert len(slices) == 36 and body["refined_by"]["job_id"] == job_id
    assert [st_["filename"] for st_ in body["stacks"]] == ["stacks[0]", "stacks[1]", "stacks[2]"]   # no client names kept
    for got, rec in zip(slices, report["slices"]):
        np.testing.assert_allclose(got["atlas_from_voxel"], rec["atlas_from_voxel"])
        assert got["included"] == rec["included"] and got["exclusion_reason"] == rec["exclusion_reason"]
        assert (got["ncc"], got["held_out_ncc"]) == (rec["ncc"], rec["held_out_ncc"])    # as docs/reconstruction.md says
        rot = np.array(got["rotation"])
        np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-9)
        assert len(got["anchor_points_mm"]) == 3 and len(got["quaternion_wxyz"]) == 4
    moved = [s["placed_by_stack_motion"] for s in slices]        # left out of the volume, placed by their stack's motion
    registered = [s["placed_by_volume"] for s in slices]         # or registered to it
    assert sum(moved) == report["left_out_placed_by_stack_motion"]
    assert sum(registered) == report["left_out_placed_by_volume"]
    assert not any(s["included"] or r for s, m, r in zip(slices, moved, registered) if m)
    assert not any(s["included"] for s, r in zip(slices, registered) if r)
    # The refined poses' expected errors. The client's poses carry none and the frame steps are off
    # (the fitted constants do not hold): the job vouches for none. With the poses' own expected
    # errors, none falls below them.
    assert all(s["refined_expected_error_mm"] is None for s in slices)
    assert report["refined_poses"]["posed"] == 0 and report["refined_poses"]["median_expected_error_mm"] is None
    with_errors = json.loads(json.dumps(case["poses"]))
    for stack in with_errors["stacks"]:
        for s in stack["slices"]:
            s["expected_error_mm"] = 3.0
    second = wait(client, submit(client, case, poses=with_errors).json()["job_id"])
    refined = [s for stack in client.get(second["poses_url"]).json()["stacks"] for s in stack["slices"]]
    assert all(s["refined_expected_error_mm"] >= 3.0 for s in refined)
    assert second["report"]["refined_poses"]["posed"] == len(refined)
    assert submit(client, case, poses=body).status_code == 202
    # The per-slice transforms: a zip of one .tfm per slice, each F A P^-1 F (docs/reconstruction.md).
    assert st["transforms_url"] == f"/v1/reconstructions/{job_id}/transforms"
    got = client.get(st["transforms_url"])
    assert got.status_code == 200 and got.headers["content-type"] == "application/zip"
    archive = zipfile.ZipFile(io.BytesIO(got.content))
    names = archive.namelist()
    assert len(names) == 37 and "transforms/slice_transforms.txt" in names
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])
    for rec in report["slices"][::7]:
        path = tmp_path / "one.tfm"
        path.write_bytes(archive.read(f"transforms/stack{rec['stack']}_slice{rec['slice']:03d}.tfm"))
        tfm = sitk.ReadTransform(str(path))
        m = np.eye(4)
        m[:3, :3] = np.reshape(tfm.GetParameters()[:9], (3, 3))
        m[:3, 3] = tfm.GetParameters()[9:]
        stack_affine = read_volume(case["files"][rec["stack"]][0]).affine
        want = flip @ stack_affine @ np.linalg.inv(np.array(rec["atlas_from_voxel"])) @ flip
        np.testing.assert_allclose(m, want, atol=1e-6)
    outputs = client.app.state.job_store.directory(job_id) / "outputs"
    listed = [name.split(" ")[0] for name in report["files"]]            # "transforms/*.tfm (36)": its pattern
    assert sorted(p.relative_to(outputs).as_posix() for p in outputs.rglob("*") if p.is_file() and p.suffix != ".tfm") \
        == sorted(n for n in listed if "*" not in n) and "poses.json" in listed   # every file the job wrote is listed
    zipped = outputs / "transforms.zip"
    zipped.unlink()                                   # a job finished before the archive existed: made on request
    again = client.get(st["transforms_url"])
    assert again.status_code == 200 and zipfile.ZipFile(io.BytesIO(again.content)).namelist() == names
    # Prometheus: the jobs by state and the runner's workers, as the store has them.
    metrics = client.get("/metrics").text
    assert re.search(r'svrnet_jobs\{status="succeeded"\} [23]\.0', metrics), metrics[-2000:]   # the two above, maybe one more
    assert re.search(r'svrnet_job_runner\{what="workers"\} [1-9]', metrics)


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)
def test_the_volume_is_served_in_a_stack_s_scanner_coordinates(client: TestClient, case: dict, tmp_path: Path) -> None:
    """``GET …/volume?stack=N``: the same voxels, the affine the report's ``stack_frames[N]`` gives
    (the case's stacks were acquired with the atlas as their scanner frame: close to the identity),
    made in memory; a stack the job does not have is a 404 naming the field, a negative index a 400,
    a volume gone with the retention a 404."""
    job_id = submit(client, case).json()["job_id"]
    st = wait(client, job_id)
    st["job_id"] = job_id
    frames = st["report"]["stack_frames"]
    assert [f["stack"] for f in frames] == [0, 1, 2] and all(f["slices"] > 0 for f in frames)
    assert all(f["motion_mm"] < 1.0 for f in frames)
    assert all(f["nifti_codes"] is not None and f["qform_from_sform"] is None for f in frames)   # NIfTI, one place
    frame = np.array(frames[1]["scanner_from_atlas"])
    np.testing.assert_allclose(frame, np.eye(4), atol=0.5)
    (tmp_path / "atlas.nii.gz").write_bytes(client.get(st["result_url"]).content)
    got = client.get(st["result_url"], params={"stack": 1})
    assert got.status_code == 200 and got.headers["content-type"] == "application/gzip"
    (tmp_path / "stack1.nii.gz").write_bytes(got.content)
    atlas, placed = read_volume(tmp_path / "atlas.nii.gz"), read_volume(tmp_path / "stack1.nii.gz")
    np.testing.assert_array_equal(placed.array, atlas.array)
    np.testing.assert_allclose(placed.affine, frame @ atlas.affine, atol=1e-4)
    assert got.headers["content-disposition"].endswith('_stack1.nii.gz"')
    outputs = client.app.state.job_store.directory(st["job_id"]) / "outputs"
    assert sorted(p.name for p in outputs.glob("volume*")) == ["volume.nii.gz"]        # nothing written beside it
    missing = client.get(st["result_url"], params={"stack": 3})
    assert missing.status_code == 404 and "stack" in missing.json()["detail"]
    negative = client.get(st["result_url"], params={"stack": -1})
    assert negative.status_code == 400 and "stack" in negative.json()["detail"]
    (outputs / "volume.nii.gz").unlink()                                               # as retention does
    gone = client.get(st["result_url"], params={"stack": 1})
    assert gone.status_code == 404 and "expired" in gone.json()["detail"]


@both
def test_stages_are_reported_in_order(client: TestClient, case: dict) -> None:
    job_id = submit(client, case, slice_order="sequential",           # the order reaches the job's stage
                    atlas_frame="true").json()["job_id"]
    stages, running = [], set()
    t0 = time.time()
    while time.time() - t0 < 180:
        st = client.get(f"/v1/reconstructions/{job_id}").json()
        if not stages or stages[-1] != st["stage"]:
            stages.append(st["stage"])
        if st["status"] == "running":
            running.add(st["stage"])
        if st["status"] in ("succeeded", "failed", "cancelled"):
            break
        time.sleep(0.05)
    assert st["status"] == "succeeded", st
    known = ["queued", "starting", "reading", "reconstructing", "stack consistency", "stack registration", "slice starting poses",
             "gaussian average", "registration 1/1", "robust weighting 1/1", "super-resolution 1/1",
             "checking starting poses", "checking slice level", "further slice-level pass", "atlas frame", "midline",
             "writing"]
    order = [known.index(s) for s in stages if s in known]
    assert order == sorted(order) and len(order) >= 2, " | ".join(map(str, stages))
    assert set(stages) <= set(known) | {"robust weighting 0/1", "super-resolution 0/1", "done", None}
    assert "done" not in running and stages[-1] == "done"                  # done once it has succeeded, not before


@both
def test_cancel_and_failure(client: TestClient, case: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    job_id = submit(client, case, svr_iterations="3").json()["job_id"]
    assert client.delete(f"/v1/reconstructions/{job_id}").status_code == 204
    st = client.get(f"/v1/reconstructions/{job_id}").json()
    assert st["status"] == "cancelled"
    assert client.get(f"/v1/reconstructions/{job_id}/volume").status_code == 409
    # No slice inside its mask (what the submission refuses, let through): the job fails, with its reason.
    monkeypatch.setattr(job_submission, "check_slices_to_use", lambda *_: None)
    job_id = submit(client, case, masks=zeroed(case, 1)).json()["job_id"]
    st = wait(client, job_id)
    assert st["status"] == "failed" and "no included slice" in st["error"] and st["coherent"] is None, st


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)
def test_a_job_with_uploaded_poses_whose_stacks_show_no_brain_the_localiser_finds_says_so(
        client: TestClient, case: dict) -> None:
    """No masks sent, and the localiser finds no brain (blank stacks): the job fails saying so and what to
    send, not with the reconstruction's "no pixel inside its mask" of masks the user never sent."""
    from service.jobs.worker import NO_BRAIN_FOUND

    st = wait(client, submit(client, case, stacks=zeroed(case, 0), with_masks=False).json()["job_id"])
    assert (st["status"], st["error"]) == ("failed", NO_BRAIN_FOUND), st


@both
def test_bad_poses_are_rejected_at_submission(client: TestClient, case: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    n = len(case["poses"]["stacks"])
    for bad in ({"stacks": case["poses"]["stacks"][:2]}, {"stacks": [{"slices": 5}] * n},
                {"stacks": [{"slices": [[1, 2]]}] * n}, {"stacks": [None] * n}, [1, 2], "{not json"):
        r = submit(client, case, poses=bad)
        assert r.status_code == 400 and "poses" in r.json()["detail"], r.text
    stack_as_poses = case["files"][0][0].read_bytes().decode("utf-8", "replace")   # a stack where poses go
    r = submit(client, case, poses=stack_as_poses)
    assert r.status_code == 400 and r.json()["detail"].startswith("poses: not JSON"), r.text
    # more JSON than poses of these stacks' slices could be, refused before it is decoded (small objects
    # decode to twenty times their text)
    for bad in ("[" * 100_000 + "]" * 100_000, "[" + ",".join(["{}"] * 200_000) + "]"):
        r = submit(client, case, poses=bad)
        assert r.status_code == 413 and r.json()["detail"].startswith("poses: "), r.text
    for value in ("nan", "inf"):                                # not a size: named so, not as out of range
        r = submit(client, case, resolution_mm=value)
        assert r.status_code == 400 and "resolution_mm" in r.json()["detail"] and "finite" in r.json()["detail"], r.text
    # Poses no scanner gives: scaled, sheared, far away, not a rigid placement; none accepted.
    for change, needle in ((lambda s: s["atlas_from_voxel"][0].__setitem__(0, 1e6), "stack 1, slice 2: atlas_from_voxel"),
                           (lambda s: s["atlas_from_voxel"][0].__setitem__(3, 5e3), "within 1000 mm"),
                           (lambda s: s["atlas_from_voxel"].__setitem__(3, [1, 2, 3, 4]), "rigid placement"),
                           (lambda s: s.__setitem__("accepted", "no"), "accepted must be true or false"),
                           (lambda s: s["atlas_from_voxel"][0].insert(0, 1.0), "a 4x4 matrix of numbers"),   # a row of 5
                           (lambda s: s["atlas_from_voxel"][0].__setitem__(0, 10 ** 400), "must be finite 4x4"),
                           (lambda s: [row.__setitem__(0, -row[0]) for row in s["atlas_from_voxel"][:3]],
                            "keeping the stack's handedness"),            # the voxels' first axis reversed
                           (lambda s: s.update(rotation=[[2, 0, 0], [0, 2, 0], [0, 0, 2]], translation_mm=[0, 0, 0]),
                            "stack 1, slice 2: rotation must be a 3x3 rotation matrix"),   # the refined frame's
                           (lambda s: s.update(rotation=[[0, 0, 0]] * 3, translation_mm=[0, 0, 0]), "rotation must be"),
                           (lambda s: s.update(rotation=np.eye(3).tolist(), translation_mm=[1, "x"]), "translation_mm")):
        bad = json.loads(json.dumps(case["poses"]))
        change(bad["stacks"][1]["slices"][2])
        r = submit(client, case, poses=bad)
        assert r.status_code == 400 and needle in r.json()["detail"], r.text
    swapped = json.loads(json.dumps(case["poses"]))                  # poses of the stacks in another order
    grids = [read_volume(stack).affine.tolist() for stack, _ in case["files"]]
    for st_, grid in zip(swapped["stacks"], grids[1:] + grids[:1]):
        st_["scanner_from_voxel"] = grid
    r = submit(client, case, poses=swapped)
    assert r.status_code == 400 and "stack 0's scanner_from_voxel is not the grid of the uploaded stack 0" in r.text
    rejected = json.loads(json.dumps(case["poses"]))
    for st_ in rejected["stacks"]:
        for s in st_["slices"]:
            s["accepted"] = False
    # Nothing to reconstruct from: masks without a voxel; poses accepted only where the masks hold none.
    r = submit(client, case, masks=zeroed(case, 1))
    assert r.status_code == 422 and r.json()["detail"].startswith("masks: no mask holds a voxel"), r.text
    r = submit(client, case, stacks=zeroed(case, 0))                     # blank stacks: a blank volume, not a result
    assert r.status_code == 422 and r.json()["detail"].startswith("stacks: no slice shows an image"), r.text
    outside, first_only = json.loads(json.dumps(case["poses"])), []
    for (_, m), st_ in zip(case["files"], outside["stacks"]):
        mask = read_volume(m)
        kept = np.moveaxis(mask.array.copy(), int(np.argmax(mask.spacing)), 0)
        kept[1:] = 0                                                     # a voxel in the first slice only
        path = m.parent / f"first_{m.name}"
        write_volume(Volume(np.moveaxis(kept, 0, int(np.argmax(mask.spacing))), mask.affine), path)
        first_only.append(path.read_bytes())
        for s in st_["slices"]:
            s["accepted"] = s["index"] != 0
    r = submit(client, case, poses=outside, masks=first_only)
    assert r.status_code == 400 and "no accepted slice holds a voxel" in r.json()["detail"], r.text
    monkeypatch.setattr(reconstructions, "MAX_POSES_BYTES", 1000)       # a file over the limit is not read
    r = submit(client, case)
    assert r.status_code == 413 and r.json()["detail"].startswith("poses: ") and "at most" in r.json()["detail"], r.text
    monkeypatch.undo()
    files = [("stacks", (s.name, s.read_bytes())) for s, _ in case["files"]]
    r = client.post("/v1/reconstructions", files=files, data={"poses": " " * 1_100_000 + json.dumps(case["poses"])})
    assert r.status_code == 413 and "as a file part" in r.json()["detail"], r.text    # a plain field over 1 MB
    assert "over 1024 KB" in r.json()["detail"]                  # the parser's own limit (a field of 1.1 MB)
    r = client.post("/v1/reconstructions", data={"poses": " " * 1_100_000})              # urlencoded, the same
    assert r.status_code == 413 and "as a file part" in r.json()["detail"], r.text
    # Poses the worker could not read (a number as text, a flag as a number) are refused now, not later.
    for change in (lambda s: s["atlas_from_voxel"][0].__setitem__(0, "1.0"), lambda s: s.__setitem__("accepted", 1)):
        bad = json.loads(json.dumps(case["poses"]))
        for st_ in bad["stacks"]:
            for s in st_["slices"]:
                change(s)
        r = submit(client, case, poses=bad)
        assert r.status_code == 400 and "poses: stack 0" in r.json()["detail"], r.text
    n_slices = len(case["poses"]["stacks"][1]["slices"])
    for order, needles in (("zigzag", ["slice_order", "interleaved-odd-first"]), (["auto", "auto"], ["2 values for 3 stacks"]),
                           (["auto", "0,1", "auto"], ["slice_order, stack 1", case["files"][1][0].name, f"stack of {n_slices} slices"])):
        r = submit(client, case, slice_order=order)
        assert r.status_code == 400 and all(n in r.json()["detail"] for n in needles), r.text
    assert not client.app.state.job_store.queued()                   # nothing left behind


@both
def test_a_retried_submission_with_its_idempotency_key_gets_the_same_job(client: TestClient, case: dict,
                                                                         caplog: pytest.LogCaptureFixture) -> None:
    """A client whose first answer was lost sends the submission again with the same key: the job the
    first made, not a second; another key, another job; a key no client would make is refused. The
    log links the submission's request id to its job."""
    headers = {"Idempotency-Key": "k-3f9c1e7a55d2b0", "X-Request-ID": "scanner-script-0001"}
    with caplog.at_level("INFO", logger="service"):
        first = submit(client, case, headers=headers)
    (line,) = [r for r in caplog.records if r.getMessage() == "job submitted"]
    assert (line.request_id, line.job_id, line.n_stacks) == ("scanner-script-0001", first.json()["job_id"], len(case["files"]))
    again = submit(client, case, headers=headers)
    assert first.status_code == again.status_code == 202
    assert again.json()["job_id"] == first.json()["job_id"] and again.headers["location"] == first.headers["location"]
    other = submit(client, case, headers={"Idempotency-Key": "k-0000000000000001"})
    assert other.json()["job_id"] != first.json()["job_id"]
    for changed in ({"stacks": zeroed(case, 0)}, {"resolution_mm": "1.5"}):    # the key of another request
        reused = submit(client, case, headers=headers, **changed)
        assert reused.status_code == 422 and first.json()["job_id"] in reused.json()["detail"], reused.text
        assert reused.json()["type"] == "/problems/idempotency-key-reused"
    refused = submit(client, case, headers={"Idempotency-Key": "short"})
    assert refused.status_code == 400 and refused.json()["detail"].startswith("Idempotency-Key:")
    two = submit(client, case, headers=[("Idempotency-Key", "k-aaaaaaaaaaaa"), ("Idempotency-Key", "k-bbbbbbbbbbbb")])
    assert two.status_code == 400 and "more than once" in two.json()["detail"], two.text
    # A retry while the first submission's files are still being read: told to ask again, not given
    # a job that a refusal of those files would delete a moment later.
    reading = {"Idempotency-Key": "k-5555555555555555"}
    client.app.state.job_store.create({"idempotency_key": deps.idempotency_digest(reading["Idempotency-Key"])})
    busy = submit(client, case, headers=reading)
    assert busy.status_code == 503 and busy.headers["retry-after"] and "still being read" in busy.json()["detail"]
    for job in (first, other):
        wait(client, job.json()["job_id"])
    documented = client.app.openapi()["paths"]["/v1/reconstructions"]["post"]["parameters"]
    assert {"name": "Idempotency-Key", "in": "header"}.items() <= documented[0].items()      # in /docs, as in the api page


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)
def test_a_job_that_finishes_while_its_delete_runs_is_deleted_whole(client: TestClient, monkeypatch) -> None:  # noqa: ANN001
    """Read as running, finished before the cancel lands: not a 'succeeded' job without its files, but
    deleted with them, as a finished job is."""
    store = client.app.state.job_store
    job = store.create({})
    assert store.claim(job.id)
    original = store.cancel

    def finishing_first(job_id: str) -> bool:
        (store.directory(job_id) / "outputs").mkdir()
        assert store.finish(job_id, {"slices": [1]})
        return original(job_id)

    monkeypatch.setattr(store, "cancel", finishing_first)
    assert client.delete(f"/v1/reconstructions/{job.id}").status_code == 204
    assert store.get(job.id) is None and not store.directory(job.id).exists()
    assert client.get(f"/v1/reconstructions/{job.id}").status_code == 404


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)     # refused before any back-end
def test_stacks_without_masks_on_a_server_without_a_localiser_are_refused_at_submission(
        queue_settings: dict[str, str], case: dict, tmp_path: Path) -> None:
    """As ``/v1/predict`` refuses them: a 400 naming ``masks`` now, not a job queued only to fail."""
    (tmp_path / "none").mkdir()
    with make_client(ModelRegistry({"default": OracleEstimator()}), localisers_dir=tmp_path / "none",
                     **queue_settings) as client:
        files = [("stacks", (s.name, s.read_bytes())) for s, _ in case["files"]]
        r = client.post("/v1/reconstructions", files=files, data={"resolution_mm": "2.0"})
        assert r.status_code == 400 and "masks" in r.json()["detail"] and "no brain localiser" in r.json()["detail"], r.text
        assert not client.app.state.job_store.queued()
        assert submit(client, case).status_code == 202                  # with masks the job is taken


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)     # the back-end plays no part
def test_a_resolution_the_masked_brain_cannot_fit_is_refused_at_submission(client: TestClient, tmp_path: Path) -> None:
    """A brain of 318 ml holds more than a reconstruction's voxels at 0.25 mm: a 400 naming
    ``resolution_mm`` and the voxel size that fits, no job queued; at that size the job is taken."""
    client.app.state.job_runner.submit = lambda job_id: None           # the submission is what is checked
    aff = np.diag([2.0, 2.0, 4.0, 1.0])
    image = np.random.default_rng(0).random((80, 80, 40)).astype(np.float32) * 100
    x, y, z = np.ogrid[:80, :80, :40]                                   # an ellipsoid brain, 100 x 80 x 76 mm: 318 ml
    mask = (((x - 39.5) / 25) ** 2 + ((y - 39.5) / 20) ** 2 + ((z - 19) / 9.5) ** 2 <= 1).astype(np.uint8)
    files = []
    for name, array in (("s.nii.gz", image), ("m.nii.gz", mask)):
        write_volume(Volume(array, aff), tmp_path / name)
        files.append(("stacks" if name == "s.nii.gz" else "masks", (name, (tmp_path / name).read_bytes())))
    r = client.post("/v1/reconstructions", files=files, data={"resolution_mm": "0.25"})
    assert r.status_code == 400, r.text
    detail = r.json()["detail"]
    assert detail.startswith("resolution_mm: ") and "110 x 90 x 86 mm, where the masks mark the brain" in detail, detail
    assert not client.app.state.job_store.queued()
    fits = re.search(r"ask for ([0-9.]+) mm or coarser", detail).group(1)
    assert client.post("/v1/reconstructions", files=files, data={"resolution_mm": fits}).status_code == 202


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)     # the back-end plays no part
def test_poses_are_matched_to_the_uploaded_stacks_by_file_name(client: TestClient, case: dict) -> None:
    """Poses naming their files are put in the uploads' order; poses of other files are refused, even
    where slice counts and voxel sizes would let them pass."""
    client.app.state.job_runner.submit = lambda job_id: None           # the stored input is what is checked
    named = json.loads(json.dumps(case["poses"]))
    for st_, (stack, _) in zip(named["stacks"], case["files"]):
        st_["filename"] = stack.name
    r = submit(client, case, poses={**named, "stacks": named["stacks"][::-1]})
    assert r.status_code == 202, r.text
    stored = json.loads((client.app.state.job_store.directory(r.json()["job_id"]) / "inputs" / "poses.json").read_text())
    assert [[s["atlas_from_voxel"] for s in st_["slices"]] for st_ in stored["stacks"]] == \
        [[s["atlas_from_voxel"] for s in st_["slices"]] for st_ in case["poses"]["stacks"]]
    for change, needle in ((lambda st: st.__setitem__("filename", "other.nii.gz"), "'other.nii.gz'"),
                           (lambda st: st.pop("filename"), "name every stack or none")):
        bad = json.loads(json.dumps(named))
        change(bad["stacks"][1])
        r = submit(client, case, poses={**bad, "stacks": bad["stacks"][::-1]})
        assert r.status_code == 400 and needle in r.json()["detail"], r.text


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)     # the back-end plays no part
def test_a_queued_job_keeps_the_decoded_voxels_not_the_files_as_sent(client: TestClient, case: dict) -> None:
    """While a job waits for a worker its folder holds each stack and mask as the submission decoded
    them (voxels, placement), not the files as sent (a DICOM file's header names the patient)."""
    from service.jobs.job_inputs import decoded_files, load_volume

    client.app.state.job_runner.submit = lambda job_id: None           # queued, never run: what is stored
    r = submit(client, case)
    assert r.status_code == 202, r.text
    inputs = client.app.state.job_store.directory(r.json()["job_id"]) / "inputs"
    assert sorted(p.name for p in inputs.iterdir() if p.suffix != ".json") == \
        sorted(f"{kind}{i}.npz" for kind in ("stack", "mask") for i in range(len(case["files"])))
    for (stack, mask), (kept_stack, kept_mask) in zip(case["files"], decoded_files(inputs)):
        for sent, kept in ((stack, kept_stack), (mask, kept_mask)):
            want, got = read_volume(sent), load_volume(kept)
            np.testing.assert_array_equal(got.array, want.array)
            np.testing.assert_allclose(got.affine, want.affine, atol=1e-6)


@both
def test_delete_of_a_finished_job_removes_it_and_a_full_queue_is_429(case: dict, queue_settings: dict) -> None:
    with make_client(ModelRegistry({"default": OracleEstimator()}), max_queued_jobs=1, retry_after_s=9,
                     **queue_settings) as client:
        client.app.state.job_runner.submit = lambda job_id: None      # the worker is busy elsewhere
        first = submit(client, case, svr_iterations="0").json()["job_id"]
        r = submit(client, case, svr_iterations="0")
        assert r.status_code == 429 and r.headers["retry-after"] == "9" and "queued" in r.json()["detail"]
        store = client.app.state.job_store
        store.delete(first)
        key = {"Idempotency-Key": "k-7777777777777777"}
        first = submit(client, case, headers=key, svr_iterations="0").json()["job_id"]   # its answer lost
        again = submit(client, case, headers=key, svr_iterations="0")                   # the queue full now
        assert again.status_code != 429, again.text         # matched to its key's job, not told the queue is full
        assert again.json().get("job_id") == first or again.json()["detail"].startswith("Idempotency-Key:")
        assert submit(client, case, headers={"Idempotency-Key": "k-8888888888888888"}, svr_iterations="0").status_code == 429
        assert store.claim(first) and store.finish(first, {"slices": []})
        assert client.get(f"/v1/reconstructions/{first}").json()["status"] == "succeeded"
        assert client.delete(f"/v1/reconstructions/{first}").status_code == 204
        assert client.get(f"/v1/reconstructions/{first}").status_code == 404


def test_a_job_queued_before_a_restart_completes_after_it(case: dict, tmp_path: Path) -> None:
    store = SqliteJobStore(tmp_path)                   # the previous server accepted a job and stopped
    job = store.create({"resolution_mm": 2.0, "svr_iterations": 0, "mc_samples": 10, "model": "default"})
    inputs = store.directory(job.id) / "inputs"
    inputs.mkdir()
    for i, (s, m) in enumerate(case["files"]):
        (inputs / f"stack{i}").write_bytes(s.read_bytes())
        (inputs / f"mask{i}").write_bytes(m.read_bytes())
    (inputs / "poses.json").write_text(json.dumps(case["poses"]))
    (inputs / "params.json").write_text(json.dumps(store.get(job.id).params))
    with make_client(ModelRegistry({"default": OracleEstimator()}), data_dir=str(tmp_path)) as client:
        st = wait(client, job.id)
    assert st["status"] == "succeeded", st


@both
def test_job_without_poses_predicts_them_with_the_model(case: dict, tiny_model_path: Path, tmp_path: Path,
                                                       queue_settings: dict) -> None:
    """No poses uploaded: the worker runs the model (here the tests' tiny real ONNX model) itself.

    Its random weights place slices anywhere, so the job either succeeds with a report of every
    slice or fails with a reason -- it never hangs or disappears.
    """
    from service.inference.estimator import OnnxPoseEstimator
    from service.inference.model_file import load_model

    registry = ModelRegistry({"tiny": OnnxPoseEstimator(load_model(tiny_model_path))})
    settings = {**queue_settings, "models_dir": str(tiny_model_path.parent.parent)}
    worker = Worker(tmp_path / "worker.log", env_of(settings)) if "queue_url" in settings else None
    with make_client(registry, **settings) as client:
        files = [("stacks", (s.name, s.read_bytes())) for s, _ in case["files"]]
        files += [("masks", (m.name, m.read_bytes())) for _, m in case["files"]]
        r = client.post("/v1/reconstructions", files=files,
                        data={"resolution_mm": "3.0", "svr_iterations": "0", "mc_samples": "5", "model": "tiny",
                              "slice_order": "interleaved"})
        assert r.status_code == 202, r.text
        st = wait(client, r.json()["job_id"])
    if worker is not None:
        worker.stop()
    assert st["seen"] & {"queued", "running"}
    if st["status"] == "succeeded":
        assert len(st["report"]["slices"]) == 36
        frame = st["report"]["atlas_frame"]        # the model re-poses slices re-cut from the volume
        assert isinstance(frame["applied"], bool) and frame["slices"] >= 0
    else:
        assert st["status"] == "failed" and st["error"]


@pytest.mark.parametrize("queue_settings", ["redis"], indirect=True)
def test_a_job_queued_while_no_worker_runs_completes_when_one_starts(case: dict, tmp_path: Path,
                                                                     queue_settings: dict) -> None:
    """Distributed: submitted through one replica with no worker anywhere, that replica stopped, the
    job polled through another replica, and done by a worker started afterwards."""
    registry = ModelRegistry({"default": OracleEstimator()})
    with make_client(registry, **queue_settings) as first:
        r = submit(first, case, svr_iterations="0")
        assert r.status_code == 202, r.text
        job_id = r.json()["job_id"]
        first.app.state.job_runner.maintain()         # a maintenance round: nothing to re-deliver, nothing lost
        st = first.get(f"/v1/reconstructions/{job_id}").json()
        assert st["status"] == "queued" and st["workers"] == 0, st    # the user can see why it waits
        # a worker killed with -9 leaves its name registered on the queue; its record expires
        import redis

        ghost = redis.Redis.from_url(queue_settings["queue_url"])
        ghost.sadd(f"rq:workers:{queue_settings['queue_name']}", "rq:worker:gone")
        assert first.get("/readyz").json()["workers"] == 0
        assert 'svrnet_job_runner{what="workers"} 0.0' in first.get("/metrics").text      # the same count
    worker = Worker(tmp_path / "worker.log", env_of(queue_settings))
    try:
        with make_client(registry, **queue_settings) as second:
            st = wait(second, job_id)
    finally:
        worker.stop()
    assert st["status"] == "succeeded" and st["attempts"] == 1, st


def wait_running(client: TestClient, job_id: str, timeout: float = 60.0) -> dict:
    """Poll until the job is inside the reconstruction (past reading), i.e. truly mid-job."""
    deadline = time.time() + timeout
    while (st := client.get(f"/v1/reconstructions/{job_id}").json())["status"] == "queued" or \
            st["stage"] in ("starting", "reading"):
        assert time.time() < deadline and st["status"] in ("queued", "running"), st
        time.sleep(0.05)
    return st


@both
def test_cancelling_a_running_job_stops_it_and_leaves_nothing(client: TestClient, case: dict) -> None:
    job_id = submit(client, case, resolution_mm="1.0", svr_iterations="3").json()["job_id"]
    assert wait_running(client, job_id)["status"] == "running"
    assert client.delete(f"/v1/reconstructions/{job_id}").status_code == 204
    folder = client.app.state.job_store.directory(job_id)
    # The worker is free again and serves the next job. There is one job worker (one process of the
    # embedded pool, one svrnet-worker): the next job runs only once the stopped run has ended, so
    # by its end whatever the stopped run still did is done, and must be gone (no fixed wait).
    assert wait(client, submit(client, case, svr_iterations="0").json()["job_id"])["status"] == "succeeded"
    st = client.get(f"/v1/reconstructions/{job_id}").json()
    assert st["status"] == "cancelled" and not folder.exists(), (st, folder.exists())


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)     # the back-end plays no part
def test_a_stated_slice_thickness_reaches_the_reconstruction_and_a_wrong_one_is_named(client: TestClient,
                                                                                       case: dict) -> None:
    n = len(case["files"])
    for values, needle in (([2.0, 3.0], f"slice_thickness_mm: 2 values for {n} stacks"),
                           ([0.01], "slice_thickness_mm[0]: Input should be greater than or equal to 0.05"),
                           (["nan"], "slice_thickness_mm[0]: Input should be a finite number")):
        r = submit(client, case, slice_thickness_mm=values)
        assert r.status_code == 400 and needle in r.json()["detail"], r.text
    r = submit(client, case, slice_thickness_mm=["4.5"])
    assert r.status_code == 202, r.text
    st = wait(client, r.json()["job_id"])
    assert st["status"] == "succeeded", st
    assert st["report"]["slice_thickness_mm"] == [4.5] * n                    # the stacks' spacing is 3 mm
    st = wait(client, submit(client, case).json()["job_id"])
    assert st["report"]["slice_thickness_mm"] != [4.5] * n                    # without it: the spacing


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)     # the back-end plays no part
def test_a_clients_extra_fields_in_its_poses_are_not_kept(client: TestClient, case: dict) -> None:
    """The refined poses are kept for the retention time: only the schema's fields of the uploaded body."""
    poses = json.loads(json.dumps(case["poses"]))
    poses["patient"] = {"name": "ZZPATIENTZZ"}
    poses["stacks"][0]["series_description"] = "ZZPATIENTZZ"
    poses["stacks"][1]["slices"][0]["note"] = "ZZPATIENTZZ"
    poses["timing_ms"] = {"ZZPATIENTZZ": 1.0}
    poses["mc_samples"] = {"hidden": "ZZPATIENTZZ"}                          # known names, other types or free text
    poses["request_id"], poses["model"] = "ZZPATIENTZZ", {"name": "ZZPATIENTZZ", "version": "1", "backbone": "b"}
    poses["stacks"][0]["slices"][1]["reason"] = "ZZPATIENTZZ"
    poses["stacks"][0]["shape"] = {"x": "ZZPATIENTZZ"}
    job_id = submit(client, case, poses=poses).json()["job_id"]
    st = wait(client, job_id)
    assert st["status"] == "succeeded", st
    refined = client.get(st["poses_url"]).text
    assert "ZZPATIENTZZ" not in refined and json.loads(refined)["stacks"][1]["slices"][0]["atlas_from_voxel"]
    assert "ZZPATIENTZZ" not in json.dumps(st["report"])                 # its provenance neither
    geometry = json.loads(refined)["stacks"][0]                            # the upload's, as the service read it
    assert geometry["shape"] == list(read_volume(case["files"][0][0]).array.shape) == [12, 36, 36]
    assert geometry["slice_axis"] == 0 and len(geometry["scanner_from_voxel"]) == 4   # its slices along axis 0


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)     # the back-end plays no part
def test_refined_poses_of_a_job_that_started_from_every_slice_are_a_valid_poses_input(client: TestClient,
                                                                                     case: dict) -> None:
    """Too few slices accepted: a job starts from all of them, and its refined poses say so by
    ``included`` while ``accepted`` stays the model's (false)."""
    refined = json.loads(json.dumps(case["poses"]))
    refined["refined_by"] = {"job_id": "earlier", "stage": "slice-to-volume reconstruction"}
    for st_ in refined["stacks"]:
        for s in st_["slices"]:
            s.update(accepted=False, included=True)
    r = submit(client, case, poses=refined)
    assert r.status_code == 202, r.text
    assert wait(client, r.json()["job_id"])["status"] == "succeeded"
    for s in refined["stacks"][0]["slices"]:
        s["included"] = False
    for st_ in refined["stacks"][1:]:
        for s in st_["slices"]:
            s["included"] = False
    assert "refined poses include no slice" in submit(client, case, poses=refined).json()["detail"]


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)     # the back-end plays no part
def test_a_predict_answer_that_accepts_no_slice_starts_the_job_as_its_own_prediction(client: TestClient,
                                                                                      case: dict) -> None:
    """``/v1/predict``'s answer for stacks without masks often accepts no slice; sent as ``poses`` it was
    refused, where the same job without poses ran from every slice: now it starts as from its own
    prediction (``started_from`` says from which slices)."""
    rejected = json.loads(json.dumps(case["poses"]))
    for st_ in rejected["stacks"]:
        for s in st_["slices"]:
            s["accepted"] = False
    r = submit(client, case, poses=rejected, atlas_frame="false", svr_iterations="1", resolution_mm="1.5")
    assert r.status_code == 202, r.text
    done = wait(client, r.json()["job_id"])
    assert done["status"] == "succeeded", done
    assert done["report"]["started_from"] == "every_slice"


@pytest.mark.parametrize("queue_settings", ["redis"], indirect=True)
def test_a_job_cancelled_while_queued_leaves_no_record_in_redis(case: dict, queue_settings: dict) -> None:
    """RQ's registry of cancelled jobs is never cleaned: the job's RQ record is deleted instead."""
    import redis

    with make_client(ModelRegistry({"default": OracleEstimator()}), **queue_settings) as client:
        job_id = submit(client, case, svr_iterations="0").json()["job_id"]      # no worker: it stays queued
        connection = redis.Redis.from_url(queue_settings["queue_url"])
        assert connection.exists(f"rq:job:{job_id}")
        assert client.delete(f"/v1/reconstructions/{job_id}").status_code == 204
        assert client.get(f"/v1/reconstructions/{job_id}").json()["status"] == "cancelled"
        assert not connection.exists(f"rq:job:{job_id}")
        assert not any(connection.zscore(key, job_id) is not None for key in connection.scan_iter("rq:*canceled*"))


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)
def test_a_stalled_job_store_holds_its_own_requests_not_the_replica(client: TestClient, monkeypatch) -> None:  # noqa: ANN001
    """A job store that does not answer (a Redis stalled for seconds) holds the requests that ask it,
    and nothing else: the liveness probe and the metrics are answered while a status read, a cancel
    and a submission's queue check wait on it (they ran on the event loop and froze the replica)."""
    import threading

    store = client.app.state.job_store
    entered, released, answered_while_stalled = threading.Semaphore(0), threading.Event(), []

    def stalled(method):  # noqa: ANN001, ANN202
        def wait_then(*args: object) -> object:
            entered.release()
            answered_while_stalled.append(released.wait(10))  # False: nothing else was answered meanwhile
            return method(*args)
        return wait_then

    monkeypatch.setattr(store, "get", stalled(store.get))
    monkeypatch.setattr(store, "queued", stalled(store.queued))
    statuses: list[int] = []
    calls = [lambda: client.get("/v1/reconstructions/abc"), lambda: client.delete("/v1/reconstructions/abc"),
             lambda: client.post("/v1/reconstructions", files=[("stacks", ("s.nii.gz", b"x"))])]
    threads = [threading.Thread(target=lambda call=call: statuses.append(call().status_code)) for call in calls]
    for t in threads:
        t.start()
    for _ in calls:
        assert entered.acquire(timeout=10)                   # all three wait on the store together
    assert client.get("/healthz").status_code == 200 and client.get("/metrics").status_code == 200
    released.set()
    for t in threads:
        t.join(10)
    assert len(answered_while_stalled) >= 3 and all(answered_while_stalled)
    assert sorted(statuses) == [404, 404, 415], statuses


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)
def test_a_submission_s_checks_of_its_volumes_hold_no_other_request(client: TestClient, case: dict,
                                                                     monkeypatch) -> None:  # noqa: ANN001
    """The whole-volume checks of a submission (masks, slices to use: seconds for many large stacks)
    run off the event loop: the liveness probe is answered while they are under way (they ran on
    the event loop and froze the replica, its streams included)."""
    import threading

    checking, released, answered_while_checking = threading.Event(), threading.Event(), []
    check = job_submission.check_slices_to_use

    def slow_check(*args: object) -> None:
        checking.set()
        answered_while_checking.append(released.wait(10))   # False: nothing else was answered meanwhile
        check(*args)

    monkeypatch.setattr(job_submission, "check_slices_to_use", slow_check)
    statuses: list[int] = []
    submitting = threading.Thread(target=lambda: statuses.append(submit(client, case).status_code))
    submitting.start()
    assert checking.wait(30)
    assert client.get("/healthz").status_code == 200
    released.set()
    submitting.join(30)
    assert answered_while_checking == [True] and statuses == [202]


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)
def test_a_full_disk_while_a_submission_s_files_are_kept_is_507_and_leaves_no_job(client: TestClient, case: dict,
                                                                                   monkeypatch) -> None:  # noqa: ANN001
    """The job's folder fills while a stack is copied into it: 507 (the server's disk, Retry-After),
    not a 500, and no job is left behind."""
    import errno
    import shutil as shutil_module

    def full(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(shutil_module, "copyfileobj", full)
    r = submit(client, case)
    assert r.status_code == 507 and r.json()["type"] == "/problems/insufficient-storage", r.text
    assert int(r.headers["Retry-After"]) > 0 and client.app.state.job_store.queued() == []


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)
@pytest.mark.parametrize("name", ["poses.json", "names.json", "params.json"])
def test_a_full_disk_while_a_submission_s_json_is_written_is_507_and_leaves_nothing(client: TestClient, case: dict,
                                                                                   name: str, monkeypatch) -> None:  # noqa: ANN001
    """The job's folder fills as its poses, the files' names or its parameters are written: 507 (the
    server's disk, Retry-After), not a 500, and neither a queued job nor its decoded stacks are left."""
    import errno

    write_text = Path.write_text

    def full(path: Path, *args: object, **kwargs: object) -> int:
        if path.name == name and "jobs" in path.parts:
            raise OSError(errno.ENOSPC, "No space left on device")
        return write_text(path, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", full)
    r = submit(client, case)
    assert r.status_code == 507 and r.json()["type"] == "/problems/insufficient-storage", r.text
    store = client.app.state.job_store
    assert int(r.headers["Retry-After"]) > 0 and store.queued() == [] and store.counts()["queued"] == 0
    assert list((store.data_dir / "jobs").iterdir()) == []


@pytest.mark.parametrize("queue_settings", ["redis"], indirect=True)
def test_a_queue_that_stops_answering_as_a_job_is_handed_to_it_is_503_and_leaves_no_job(
        client: TestClient, case: dict, monkeypatch) -> None:  # noqa: ANN001
    """Redis goes away while a submission's files are read (a restart, a fail-over): handing the job
    to the queue fails. The client is told to come back (503, Retry-After), not a 500, and no job is
    left behind (it stayed queued, never to run, until the upkeep failed it as interrupted); a retry
    with the same key then makes its job."""
    import redis

    runner = client.app.state.job_runner
    enqueue = runner.queue.enqueue

    def unanswered(*args: object, **kwargs: object) -> None:
        raise redis.ConnectionError("Connection refused")

    monkeypatch.setattr(runner.queue, "enqueue", unanswered)
    key = "k-8888888888888888"
    r = submit(client, case, headers={"Idempotency-Key": key})
    assert r.status_code == 503 and r.json()["type"] == "/problems/store-unavailable", r.text
    assert int(r.headers["Retry-After"]) > 0
    assert client.app.state.job_store.queued() == [] and client.app.state.job_store.ids("failed") == []
    monkeypatch.setattr(runner.queue, "enqueue", enqueue)
    r = submit(client, case, headers={"Idempotency-Key": key})
    assert r.status_code == 202 and r.json()["status"] == "queued", r.text


@pytest.mark.parametrize("queue_settings", ["redis"], indirect=True)
def test_a_retry_of_a_submission_its_replica_abandoned_is_told_at_once(client: TestClient, case: dict,
                                                                        monkeypatch) -> None:  # noqa: ANN001
    """A replica stopped while it read a keyed submission: the job was stored, never queued. A retry
    with the key waits while a replica holds the submission, and once none has for the lease the job
    is failed as interrupted and the retry gets it at once, not a 503 for an hour."""
    from service.jobs import store as store_module
    from service.jobs.store import SUBMISSION_LEASE_S

    key = "k-7777777777777777"
    store = client.app.state.job_store
    orphan = store.create({"idempotency_key": deps.idempotency_digest(key)})
    store.hold_submission(orphan.id)                            # its replica still reading it
    later = time.time() + SUBMISSION_LEASE_S + 1
    monkeypatch.setattr(store_module.time, "time", lambda: later)
    assert submit(client, case, headers={"Idempotency-Key": key}).status_code == 503
    store.redis.delete(f"{store.prefix}submitting:{orphan.id}")   # the replica stopped: no renewal
    r = submit(client, case, headers={"Idempotency-Key": key})
    assert r.status_code == 202 and r.json() == {"job_id": orphan.id, "status": "failed",
                                                 "status_url": f"/v1/reconstructions/{orphan.id}"}, r.text
    assert "interrupted" in client.get(f"/v1/reconstructions/{orphan.id}").json()["error"]


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)
def test_a_submission_given_up_while_its_files_were_read_is_told_not_queued(client: TestClient, case: dict,
                                                                              monkeypatch) -> None:  # noqa: ANN001
    """The store failed the job while its files were read (its replica's lease lapsed, a retry found it
    abandoned): the submission is answered 503 saying so, and nothing is queued or written for it."""
    from service.jobs.runner import INTERRUPTED

    store = client.app.state.job_store
    monkeypatch.setattr(job_submission, "check_slices_to_use",
                        lambda uploads, accepted: [store.fail(j, INTERRUPTED) for j in store.ids("queued")])
    r = submit(client, case, headers={"Idempotency-Key": "k-8888888888888888"})
    assert r.status_code == 503 and "gave this submission up" in r.json()["detail"], r.text
    assert store.queued() == [] and all(store.get(j).status == "failed" for j in store.ids("failed"))


def test_an_idempotency_key_is_each_clients_own(case: dict) -> None:
    """Two clients (two API keys) that happen to send one idempotency key: the second gets a job of
    its own, not a 422 naming the first client's job (nor that job)."""
    with make_client(ModelRegistry({"default": OracleEstimator()}), api_keys="k-lab-one,k-lab-two") as client:
        key = "k-3333333333333333"
        first = submit(client, case, headers={"Idempotency-Key": key, "Authorization": "Bearer k-lab-one"},
                       svr_iterations="0")
        again = submit(client, case, headers={"Idempotency-Key": key, "Authorization": "Bearer k-lab-one"},
                       svr_iterations="0")
        other = submit(client, case, headers={"Idempotency-Key": key, "X-API-Key": "k-lab-two"}, svr_iterations="1")
    assert first.status_code == again.status_code == other.status_code == 202, other.text
    assert again.json()["job_id"] == first.json()["job_id"] != other.json()["job_id"]


def test_a_job_is_its_clients_alone(case: dict) -> None:
    """On a server with API keys a job answers only the key that submitted it: another key gets the
    404 of an unknown job for its status, its results and its deletion, and the job stays whole."""
    with make_client(ModelRegistry({"default": OracleEstimator()}), api_keys="k-lab-one,k-lab-two") as client:
        made = submit(client, case, headers={"Authorization": "Bearer k-lab-one"}, svr_iterations="0")
        assert made.status_code == 202, made.text
        url = made.json()["status_url"]
        one, two = {"Authorization": "Bearer k-lab-one"}, {"X-API-Key": "k-lab-two"}
        for path in ("", "/volume", "/poses", "/transforms", "/preview.png"):
            r = client.get(url + path, headers=two)
            assert r.status_code == 404 and r.headers["content-type"] == "application/problem+json", (path, r.text)
            assert r.json()["detail"] == f"job_id: no job {made.json()['job_id']!r}"     # as for a job never made
        assert client.delete(url, headers=two).status_code == 404
        assert client.get(url, headers=one).json()["job_id"] == made.json()["job_id"]
        assert client.delete(url, headers=one).status_code == 204
        older = client.app.state.job_store.create({"resolution_mm": 0.8})      # made before jobs had owners
        assert client.get(f"/v1/reconstructions/{older.id}", headers=two).json()["status"] == "queued"


def test_a_result_deleted_after_its_handler_looked_is_a_404_not_a_500(tmp_path: Path) -> None:
    """A download racing the job's deletion or the retention clean-up (the file gone between the
    handler's check and the response's own): a 404 problem, not the server error Starlette raises."""
    from starlette.applications import Starlette
    from starlette.routing import Route

    gone = tmp_path / "volume.nii.gz"
    app = Starlette(routes=[Route("/v", lambda request: reconstructions.Download(gone, filename="volume.nii.gz"))])
    with LocalClient(app, raise_server_exceptions=False) as client:
        r = client.get("/v")
    assert r.status_code == 404 and r.headers["content-type"] == "application/problem+json", r.text
    assert "deleted or expired" in r.json()["detail"]
