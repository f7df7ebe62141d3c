"""A job's uploads (raw stacks with their headers, their names) are deleted as soon as the job
ends, whatever its outcome; only what the results need is kept."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.api import job_submission
from service.inference.registry import ModelRegistry
from service.jobs.sqlite_store import SqliteJobStore
from tests.api.conftest import OracleEstimator, make_client
from tests.jobs.conftest import BACKENDS
from tests.jobs.test_jobs_api import case, submit, wait, zeroed  # noqa: F401 - fixture

PATIENT = b"Doe^Jane"


@pytest.fixture
def client(queue_settings: dict[str, str], workers: list):  # noqa: ANN201
    with make_client(ModelRegistry({"default": OracleEstimator()}), **queue_settings) as c:
        yield c


def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def _assert_no_upload_left(folder: Path) -> None:
    assert not (folder / "inputs").exists(), _files(folder)
    for p in folder.rglob("*"):
        if p.is_file():
            data = p.read_bytes()
            assert b"names.json" not in data and b"s0.nii.gz" not in data, p


@pytest.mark.parametrize("queue_settings", BACKENDS, indirect=True)
def test_a_succeeded_job_keeps_only_its_results(client: TestClient, case: dict) -> None:
    job_id = submit(client, case, svr_iterations="0").json()["job_id"]
    folder = client.app.state.job_store.directory(job_id)
    assert (folder / "inputs" / "names.json").exists()            # while it is queued or running
    assert wait(client, job_id)["status"] == "succeeded"
    _assert_no_upload_left(folder)
    assert {"outputs/volume.nii.gz", "outputs/preview.png", "outputs/report.json"} <= set(_files(folder))
    assert client.get(f"/v1/reconstructions/{job_id}/volume").status_code == 200


@pytest.mark.parametrize("queue_settings", BACKENDS, indirect=True)
def test_a_failed_job_keeps_nothing_of_its_uploads(client: TestClient, case: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(job_submission, "check_slices_to_use", lambda *_: None)      # a job the worker fails
    job_id = submit(client, case, masks=zeroed(case, 1)).json()["job_id"]
    assert wait(client, job_id)["status"] == "failed"
    _assert_no_upload_left(client.app.state.job_store.directory(job_id))


def test_a_job_failed_by_too_many_restarts_keeps_nothing(tmp_path: Path) -> None:
    store = SqliteJobStore(tmp_path)
    job = store.create({"resolution_mm": 2.0})
    (store.directory(job.id) / "inputs").mkdir()
    (store.directory(job.id) / "inputs" / "stack0").write_bytes(PATIENT)
    for _ in range(2):
        assert store.claim(job.id)
        (store.directory(job.id) / "outputs").mkdir(exist_ok=True)          # a run killed as it wrote its results
        (store.directory(job.id) / "outputs" / "volume.nii.gz").write_bytes(PATIENT)
        store.recover()
    assert store.get(job.id).status == "failed"
    assert not (store.directory(job.id) / "inputs").exists()
    assert not (store.directory(job.id) / "outputs").exists()              # a failed job's, never served


def test_a_job_folder_whose_record_was_lost_goes_after_the_grace(tmp_path: Path) -> None:
    """As after a Redis restarted without persistence: the uploads would otherwise stay for ever."""
    import os
    import time

    store = SqliteJobStore(tmp_path)
    kept = store.create({})
    (store.directory(kept.id) / "inputs").mkdir(parents=True)
    orphan, fresh = tmp_path / "jobs" / "0f", tmp_path / "jobs" / "1e"
    for folder in (orphan, fresh):
        (folder / "inputs").mkdir(parents=True)
        (folder / "inputs" / "names.json").write_bytes(PATIENT)
    old = time.time() - 7200
    for folder in (orphan, store.directory(kept.id)):
        os.utime(folder, (old, old))
    assert store.sweep_orphans(grace_s=3600) == ["0f"]
    assert not orphan.exists() and fresh.exists() and store.directory(kept.id).exists()
