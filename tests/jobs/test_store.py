"""The job store: lifecycle, cancellation, restart recovery, retention."""

from __future__ import annotations

import time
from pathlib import Path

from service.jobs.store import JobStore


def test_lifecycle_and_claim_is_atomic(tmp_path: Path) -> None:
    store = JobStore(tmp_path)
    job = store.create({"resolution_mm": 0.8})
    assert job.status == "queued" and store.directory(job.id).is_dir()
    assert store.claim(job.id) and not store.claim(job.id)
    store.update(job.id, stage="reconstructing", progress=0.5)
    got = store.get(job.id)
    assert (got.status, got.stage, got.progress, got.attempts) == ("running", "reconstructing", 0.5, 1)
    store.update(job.id, status="succeeded", progress=1.0, report={"slices": [1, 2]})
    assert store.get(job.id).report == {"slices": [1, 2]}
    assert store.get("nope") is None and store.ping()


def test_cancel_deletes_files_and_stops_claims(tmp_path: Path) -> None:
    store = JobStore(tmp_path)
    job = store.create({})
    (store.directory(job.id) / "inputs").mkdir()
    store.cancel(job.id)
    assert store.get(job.id).status == "cancelled" and not store.directory(job.id).exists()
    assert not store.claim(job.id) and store.is_cancelled(job.id)


def test_restart_requeues_running_jobs_then_fails_them_after_max_attempts(tmp_path: Path) -> None:
    store = JobStore(tmp_path)
    queued, running = store.create({}), store.create({})
    store.claim(running.id)
    reopened = JobStore(tmp_path)                     # a new server process
    assert set(reopened.recover(max_attempts=2)) == {queued.id, running.id}
    assert reopened.get(running.id).status == "queued"
    reopened.claim(running.id)                        # second attempt, interrupted again
    assert reopened.recover(max_attempts=2) == [queued.id]
    failed = reopened.get(running.id)
    assert failed.status == "failed" and "restart" in failed.error


def test_retention_expires_only_finished_jobs(tmp_path: Path) -> None:
    store = JobStore(tmp_path)
    old, live = store.create({}), store.create({})
    store.update(old.id, status="succeeded")
    time.sleep(0.05)
    assert store.expire(retention_s=0.01) == [old.id]
    assert store.get(old.id) is None and not store.directory(old.id).exists()
    assert store.get(live.id).status == "queued"


def test_a_job_cancelled_while_it_writes_does_not_end_succeeded(tmp_path: Path) -> None:
    store = JobStore(tmp_path)
    job = store.create({})
    assert store.claim(job.id)
    store.cancel(job.id)
    assert not store.finish(job.id, {"slices": []}) and store.get(job.id).status == "cancelled"
    other = store.create({})
    assert store.claim(other.id) and store.finish(other.id, {"slices": [1]})
    assert (store.get(other.id).status, store.get(other.id).report) == ("succeeded", {"slices": [1]})
