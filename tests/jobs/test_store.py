"""The job stores, both back-ends through one interface: lifecycle, atomic claims, cancellation,
failure, retention; and the embedded store's recovery after a restart."""

from __future__ import annotations

import sqlite3
import time
from pathlib import Path

import pytest

from service.jobs.sqlite_store import SqliteJobStore
from service.jobs.store import JobStore
from tests.jobs.conftest import BACKENDS

both = pytest.mark.parametrize("queue_settings", BACKENDS, indirect=True)


@both
def test_lifecycle_and_claim_is_atomic(store: JobStore) -> None:
    job = store.create({"resolution_mm": 0.8})
    assert job.status == "queued" and store.directory(job.id).is_dir() and store.queued() == [job.id]
    assert job.attempts == 0 and job.started_at is None and job.params == {"resolution_mm": 0.8}
    assert store.claim(job.id) and not store.claim(job.id)
    store.update(job.id, stage="reconstructing", progress=0.5)
    got = store.get(job.id)
    assert (got.status, got.stage, got.progress, got.attempts) == ("running", "reconstructing", 0.5, 1)
    assert got.started_at is not None and store.queued() == [] and store.ids("running") == [job.id]
    assert store.finish(job.id, {"slices": [1, 2]}) and not store.finish(job.id, {"slices": []})
    got = store.get(job.id)
    assert (got.status, got.progress, got.report) == ("succeeded", 1.0, {"slices": [1, 2]})
    assert store.counts() == {"queued": 0, "running": 0, "succeeded": 1, "failed": 0, "cancelled": 0}
    assert store.get("nope") is None and store.ping()
    with pytest.raises(ValueError, match="only stage"):
        store.update(job.id, status="queued")          # states change only through the transitions


@both
def test_a_run_s_late_progress_report_does_not_show_an_ended_job_at_work(store: JobStore) -> None:
    """A worker reads its job as running, the job is cancelled (or ends), then the report lands."""
    cancelled, done = store.create({}), store.create({})
    for job in (cancelled, done):
        assert store.claim(job.id)
    store.cancel(cancelled.id)
    assert store.finish(done.id, {"slices": []})
    for job, status, progress in ((cancelled, "cancelled", 0.0), (done, "succeeded", 1.0)):
        store.update(job.id, stage="registration 2/3", progress=0.4)
        got = store.get(job.id)
        assert got.status == status and got.stage != "registration 2/3" and got.progress == progress, got
        ended = got.updated_at                                # the queue's late hand-over time moves no expiry
        store.update(job.id, submitted_at=ended + 5.0)
        assert store.get(job.id).updated_at == ended and store.get(job.id).submitted_at == ended + 5.0


@both
def test_submissions_with_one_key_at_the_same_moment_make_one_job(store: JobStore) -> None:
    """Eight submissions with one idempotency key at once: one job made, the others given it; a
    submission without a key always makes its own."""
    from concurrent.futures import ThreadPoolExecutor
    from threading import Barrier

    start = Barrier(8)

    def submit(_: int) -> tuple[str, bool]:
        start.wait()
        job, made = store.create_once({"resolution_mm": 0.8, "idempotency_key": "k" * 64})
        return job.id, made

    with ThreadPoolExecutor(8) as pool:
        answers = list(pool.map(submit, range(8)))
    assert sum(made for _, made in answers) == 1 and len({job_id for job_id, _ in answers}) == 1
    assert store.queued() == [answers[0][0]] and store.job_for_key("k" * 64).id == answers[0][0]
    assert store.create_once({})[1] and store.create_once({})[1] and len(store.queued()) == 3
    folders = sorted(p.name for p in (store.data_dir / "jobs").iterdir())
    assert folders == sorted(store.queued())                  # the ids drawn for the seven retries left no folder


@both
def test_submissions_at_the_same_moment_never_queue_more_than_the_limit(store: JobStore) -> None:
    """Twelve submissions at once against a limit of five queued jobs (two queued already): three are
    made, nine refused with the queue's 429, and only the made jobs have folders."""
    from concurrent.futures import ThreadPoolExecutor
    from threading import Barrier

    from service.core.errors import QueueFull

    store.create({}), store.create({})
    start = Barrier(12)

    def submit(k: int) -> str | None:
        start.wait()
        try:
            return store.create_once({"resolution_mm": 0.8} if k % 2 else {"idempotency_key": f"k-{k:016d}"}, 5)[0].id
        except QueueFull as refused:
            assert refused.status == 429
            return None

    with ThreadPoolExecutor(12) as pool:
        made = [j for j in pool.map(submit, range(12)) if j is not None]
    assert len(made) == 3 and len(store.queued()) == 5
    assert sorted(p.name for p in (store.data_dir / "jobs").iterdir()) == sorted(store.queued())


@both
def test_a_store_whose_jobs_folder_is_gone_is_not_ready(store: JobStore, tmp_path: Path) -> None:
    """The jobs' folder unmounted or gone (the database or Redis still answering): the store's ping,
    which ``/readyz`` asks, says it cannot take jobs."""
    assert store.ping()
    store.data_dir = tmp_path / "unmounted"
    assert not store.ping()


@both
def test_a_store_on_a_full_disk_is_not_ready(store: JobStore, monkeypatch: pytest.MonkeyPatch) -> None:
    """A data folder that can be written but has no room (the volume full): the ping says the store
    cannot take jobs, as for a read-only folder (it answered ready, and every submission failed)."""
    import shutil as shutil_module
    from collections import namedtuple

    assert store.ping()
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil_module, "disk_usage", lambda path: usage(10 << 30, (10 << 30) - (1 << 20), 1 << 20))
    assert not store.ping()


def test_a_submission_the_database_refuses_leaves_no_job_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A full disk refuses the new job's record (503): the folder made for the job goes with it, by
    either way of submitting."""
    from service.core.errors import StoreUnavailable

    store = SqliteJobStore(tmp_path)

    def refused(self: SqliteJobStore) -> None:
        raise StoreUnavailable("the job store's database cannot be used (database or disk is full)")

    monkeypatch.setattr(SqliteJobStore, "_db", refused)
    for submit in (lambda: store.create({}), lambda: store.create_once({"idempotency_key": "k"}),
                   lambda: store.create_once({}, max_queued=4)):
        with pytest.raises(StoreUnavailable):
            submit()
    assert not list((tmp_path / "jobs").iterdir())


@both
def test_a_redelivered_job_may_be_claimed_while_running_but_not_once_finished(store: JobStore) -> None:
    job = store.create({})
    assert store.claim(job.id) == 1 and not store.claim(job.id)
    assert store.claim(job.id, redelivered=True) == 2 and store.get(job.id).attempts == 2
    # The superseded first run can neither finish nor fail the job; the second one can.
    assert not store.finish(job.id, {"run": 1}, attempt=1) and not store.fail(job.id, "x", attempt=1)
    assert store.get(job.id).status == "running"
    assert store.finish(job.id, {"run": 2}, attempt=2) and store.get(job.id).report == {"run": 2}
    assert not store.claim(job.id, redelivered=True)


@both
def test_a_run_whose_job_was_put_back_in_the_queue_under_it_may_still_finish_it(store: JobStore) -> None:
    """The queue took a live run for lost and put its job back (its attempts unchanged): that run's
    finish still ends the job, unless a later run claimed it meanwhile; a run whose job was handed
    back by a stopping worker (the run not counted) never does, nor does a finish without an attempt."""
    put_back, claimed_again, handed_back = store.create({}), store.create({}), store.create({})
    for job in (put_back, claimed_again, handed_back):
        assert store.claim(job.id) == 1
    if isinstance(store, SqliteJobStore):                 # its worker processes lost: the pool's recovery
        store.recover(max_attempts=2, cause="lost worker", spared=[handed_back.id])
    else:                                                 # RQ's clean-up, seen by a replica's reconcile
        assert store.back_in_queue(put_back.id, 1) and store.back_in_queue(claimed_again.id, 1)
        assert store.hand_back(handed_back.id)
    assert [store.get(j.id).status for j in (put_back, claimed_again, handed_back)] == ["queued"] * 3
    assert store.claim(claimed_again.id) == 2
    assert not store.finish(put_back.id, {"run": 1}) and not store.finish(handed_back.id, {"run": 1}, attempt=1)
    assert store.finish(put_back.id, {"run": 1}, attempt=1) and store.get(put_back.id).report == {"run": 1}
    assert not store.finish(claimed_again.id, {"run": 1}, attempt=1)
    assert store.finish(claimed_again.id, {"run": 2}, attempt=2)
    assert store.get(handed_back.id).status == "queued" and store.queued() == [handed_back.id]


@both
def test_cancel_deletes_files_and_stops_claims(store: JobStore) -> None:
    job = store.create({})
    (store.directory(job.id) / "inputs").mkdir()
    assert store.cancel(job.id)
    assert store.get(job.id).status == "cancelled" and not store.directory(job.id).exists()
    assert not store.claim(job.id) and not store.claim(job.id, redelivered=True) and store.is_cancelled(job.id)
    assert not store.fail(job.id, "late") and store.get(job.id).error is None


@both
def test_a_job_that_finished_before_its_cancel_keeps_its_results(store: JobStore) -> None:
    """The cancel of a job read as running that has finished since: refused, its files kept (the API
    then deletes the job whole, as it deletes a finished one)."""
    job = store.create({})
    assert store.claim(job.id)
    (store.directory(job.id) / "outputs").mkdir()
    (store.directory(job.id) / "outputs" / "volume.nii.gz").write_bytes(b"v")
    assert store.finish(job.id, {"slices": [1]})
    assert not store.cancel(job.id)
    assert store.get(job.id).status == "succeeded" and (store.directory(job.id) / "outputs" / "volume.nii.gz").exists()


@both
def test_failure_keeps_the_reason_and_is_final(store: JobStore) -> None:
    job = store.create({})
    assert store.claim(job.id) and store.fail(job.id, "no included slice")
    got = store.get(job.id)
    assert (got.status, got.error) == ("failed", "no included slice")
    assert not store.finish(job.id, {}) and not store.claim(job.id, redelivered=True)
    queued = store.create({})
    assert store.fail(queued.id, "lost") and store.queued() == []


@both
def test_retention_expires_only_finished_jobs(store: JobStore) -> None:
    old, live = store.create({}), store.create({})
    assert store.claim(old.id) and store.finish(old.id, {})
    time.sleep(0.05)
    assert store.expire(retention_s=0.01) == [old.id]
    assert store.get(old.id) is None and not store.directory(old.id).exists()
    assert store.get(live.id).status == "queued" and store.expire(retention_s=0.01) == []


@both
def test_uploads_of_ended_jobs_are_discarded_whoever_ended_them(store: JobStore) -> None:
    ended, live = store.create({}), store.create({})
    for job in (ended, live):
        (store.directory(job.id) / "inputs").mkdir()
        (store.directory(job.id) / "inputs" / "stack_0.nii.gz").write_bytes(b"x")
    assert store.claim(ended.id) and store.fail(ended.id, "a worker on another data folder")
    assert store.discard_ended_inputs() == [ended.id] and store.discard_ended_inputs() == []
    assert not (store.directory(ended.id) / "inputs").exists() and store.directory(ended.id).is_dir()
    assert (store.directory(live.id) / "inputs" / "stack_0.nii.gz").exists()     # a queued job keeps them


@both
def test_results_of_failed_or_cancelled_jobs_are_discarded_whoever_ended_them(store: JobStore) -> None:
    """What a run stopped from outside wrote of its results (a worker killed as it wrote them, after
    its job was failed or cancelled) goes at the upkeep: those jobs never serve them. A succeeded
    job's results stay."""
    failed, cancelled, done = store.create({}), store.create({}), store.create({})
    for job in (failed, cancelled, done):
        assert store.claim(job.id)
    assert store.fail(failed.id, "the worker running it was lost") and store.cancel(cancelled.id)
    assert store.finish(done.id, {})
    for job in (failed, cancelled, done):
        (store.directory(job.id) / "outputs").mkdir(parents=True)
        (store.directory(job.id) / "outputs" / "volume.nii.gz").write_bytes(b"Doe^Jane")
    assert sorted(store.discard_ended_inputs()) == sorted([failed.id, cancelled.id])
    assert store.discard_ended_inputs() == []
    assert not (store.directory(failed.id) / "outputs").exists()
    assert not (store.directory(cancelled.id) / "outputs").exists()
    assert (store.directory(done.id) / "outputs" / "volume.nii.gz").exists()


def test_a_worker_without_the_uploads_fails_the_job_saying_why(tmp_path: Path) -> None:
    from service.jobs.worker import MISSING_UPLOADS, run_job

    store = SqliteJobStore(tmp_path / "api")
    job = store.create({})
    (store.directory(job.id) / "inputs").mkdir()
    (store.directory(job.id) / "inputs" / "params.json").write_text("{}")
    elsewhere = SqliteJobStore(tmp_path / "api")
    elsewhere.data_dir = tmp_path / "worker"                   # the records shared, not the folder
    run_job(elsewhere, tmp_path / "models", job.id)
    got = store.get(job.id)
    assert (got.status, got.error) == ("failed", MISSING_UPLOADS) and "SVRNET_DATA_DIR" in got.error


@both
def test_a_job_cancelled_while_it_writes_does_not_end_succeeded(store: JobStore) -> None:
    job = store.create({})
    assert store.claim(job.id)
    store.cancel(job.id)
    assert not store.finish(job.id, {"slices": []}) and store.get(job.id).status == "cancelled"
    other = store.create({})
    assert store.claim(other.id) and store.finish(other.id, {"slices": [1]})
    assert (store.get(other.id).status, store.get(other.id).report) == ("succeeded", {"slices": [1]})


@both
def test_delete_removes_record_and_files(store: JobStore) -> None:
    job = store.create({})
    store.delete(job.id)
    assert store.get(job.id) is None and not store.directory(job.id).exists() and store.queued() == []


def test_a_cancel_on_a_full_disk_frees_the_job_s_files_to_make_its_write(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """The database refuses the cancel's write until the job's files are gone (their space is what
    the write needs): the uploads go first, and the job is cancelled. A job that has ended is left as
    it is, its results kept, and the refusal stands (503)."""
    from service.core.errors import StoreUnavailable

    store = SqliteJobStore(tmp_path)
    running, ended = store.create({}), store.create({})
    assert store.claim(running.id) and store.claim(ended.id) and store.finish(ended.id, {})
    for job, part in ((running, "inputs"), (ended, "outputs")):
        (store.directory(job.id) / part).mkdir(parents=True)
        (store.directory(job.id) / part / "stack0.npz").write_bytes(b"patient data")
    real = SqliteJobStore._write

    def full_while_files(self: SqliteJobStore, sql: str, args: tuple) -> bool:
        if any(store.directory(j.id).exists() for j in (running, ended) if j.id in args):
            raise StoreUnavailable("the job store's database cannot be used (database or disk is full)")
        return real(self, sql, args)

    monkeypatch.setattr(SqliteJobStore, "_write", full_while_files)
    assert store.cancel(running.id)
    assert store.get(running.id).status == "cancelled" and not store.directory(running.id).exists()
    with pytest.raises(StoreUnavailable):
        store.cancel(ended.id)
    assert store.get(ended.id).status == "succeeded" and (store.directory(ended.id) / "outputs" / "stack0.npz").exists()


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)
def test_a_deleted_or_expired_job_leaves_no_trace_in_the_database_files(store: JobStore) -> None:
    marker = b"key-of-a-deleted-job"
    for end in ("delete", "expire"):
        job = store.create({"idempotency_key": marker.decode() + end})
        assert store.claim(job.id) and store.finish(job.id, {"note": marker.decode() + end})
        reader = sqlite3.connect(store.data_dir / "jobs.sqlite3", isolation_level=None)
        reader.execute("BEGIN")
        reader.execute("SELECT COUNT(*) FROM jobs").fetchone()       # a read under way: the deletion does not wait
        started = time.perf_counter()
        store.delete(store.create({}).id)
        assert time.perf_counter() - started < 10          # not the 30 s a write waits for a lock
        reader.close()                                                 # the next deletion's checkpoint does it
        if end == "delete":
            store.delete(job.id)
        else:
            time.sleep(0.05)
            assert store.expire(retention_s=0.01) == [job.id]
        files = list(store.data_dir.glob("jobs.sqlite3*"))
        assert files and all(marker + end.encode() not in f.read_bytes() for f in files), end
        assert all(job.id.encode() not in f.read_bytes() for f in files), end


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)
def test_restart_requeues_running_jobs_then_fails_them_after_max_attempts(store: JobStore, tmp_path: Path,
                                                                        caplog: pytest.LogCaptureFixture) -> None:
    queued, running = store.create({}), store.create({})
    store.claim(running.id)
    reopened = SqliteJobStore(store.data_dir)         # a new server process
    assert set(reopened.recover(max_attempts=2)) == {queued.id, running.id}
    assert reopened.get(running.id).status == "queued"
    reopened.claim(running.id)                        # second attempt, interrupted again
    assert reopened.recover(max_attempts=2) == [queued.id]
    failed = reopened.get(running.id)
    assert failed.status == "failed" and "restart" in failed.error
    assert f"job {running.id} failed: interrupted by a server restart" in caplog.text       # the log says so too


@pytest.mark.parametrize("queue_settings", ["redis"], indirect=True)
def test_the_queue_maintenance_fails_orphaned_and_given_up_jobs_with_reasons(queue_settings: dict) -> None:
    """What a replica's maintenance does with jobs the queue cannot run: a submission left half done
    by a stopped replica (after a grace period), a job the queue no longer knows."""
    from service.core.settings import Settings
    from service.jobs.runner import INTERRUPTED
    from service.jobs.backends import open_backend

    store, runner = open_backend(Settings(**queue_settings))
    orphan, lost, healthy = (store.create({}) for _ in range(3))
    for job in (orphan, lost):
        (store.directory(job.id) / "inputs").mkdir()
    (store.directory(lost.id) / "outputs").mkdir()          # what a lost run wrote of its results
    store.update(lost.id, submitted_at=time.time())      # handed over, but the queue has no record of it
    runner.submit(healthy.id)
    runner.submit_grace_s = 2.0
    time.sleep(2.1)
    uploading = store.create({})                          # created just now: within the grace (2 s of slack)
    assert sorted(runner.reconcile()) == sorted([orphan.id, lost.id])
    assert store.get(orphan.id).error == INTERRUPTED and "lost the job" in store.get(lost.id).error
    assert not (store.directory(orphan.id) / "inputs").exists()
    assert not (store.directory(lost.id) / "inputs").exists() and not (store.directory(lost.id) / "outputs").exists()
    assert store.get(uploading.id).status == "queued" and store.get(healthy.id).status == "queued"
    runner.shutdown()


@pytest.mark.parametrize("queue_settings", ["redis"], indirect=True)
def test_a_superseded_runs_return_does_not_fail_the_run_in_progress(queue_settings: dict,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    # A worker silent too long has its job re-delivered; when the first run, alive after all, stops
    # at its next stage, RQ marks the shared job finished under the second run, which goes on.
    from rq.job import Job as RqJob
    from rq.job import JobStatus

    from service.core.settings import Settings
    from service.jobs import rq_runner
    from service.jobs.backends import open_backend

    settings = Settings(**queue_settings)
    store, runner = open_backend(settings)
    job = store.create({})
    runner.submit(job.id)
    assert store.claim(job.id) == 1 and store.claim(job.id, redelivered=True) == 2     # the second run
    RqJob.fetch(job.id, connection=runner.connection).set_status(JobStatus.FINISHED)   # the first run's return
    assert runner.reconcile() == [] and store.get(job.id).status == "running"
    later = time.time() + settings.job_timeout_h * 3600 + settings.worker_lost_after_s + settings.worker_heartbeat_s + 1
    monkeypatch.setattr(rq_runner.time, "time", lambda: later)                         # no run can be alive now
    assert runner.reconcile() == [job.id]
    assert store.get(job.id).error == "the worker ended without completing the job"
    # the finished record expires (result_ttl) while the second run goes on: not taken for a lost job
    monkeypatch.undo()
    again = store.create({})
    runner.submit(again.id)
    assert store.claim(again.id) == 1 and store.claim(again.id, redelivered=True) == 2
    RqJob.fetch(again.id, connection=runner.connection).delete()
    assert runner.reconcile() == [] and store.get(again.id).status == "running"
    monkeypatch.setattr(rq_runner.time, "time", lambda: later)
    assert runner.reconcile() == [again.id] and "lost the job" in store.get(again.id).error
    runner.shutdown()


@pytest.mark.parametrize("queue_settings", ["redis"], indirect=True)
def test_a_job_the_queue_took_back_from_a_lost_worker_shows_queued(queue_settings: dict) -> None:
    """RQ's clean-up puts a lost worker's job back in the queue: the store shows it queued again (it
    showed `running`, its stage frozen, for as long as no worker came), its lost run counted; a later
    run that claimed it meanwhile is left running."""
    from rq.job import Job as RqJob
    from rq.job import JobStatus

    from service.core.settings import Settings
    from service.jobs.backends import open_backend

    store, runner = open_backend(Settings(**queue_settings))
    job = store.create({})
    runner.submit(job.id)
    assert store.claim(job.id) == 1
    RqJob.fetch(job.id, connection=runner.connection).set_status(JobStatus.QUEUED)     # the registry's clean-up
    assert runner.reconcile() == []
    back = store.get(job.id)
    assert back.status == "queued" and "worker was lost" in back.stage and back.attempts == 1
    assert store.claim(job.id) == 2                                   # the next worker's run
    assert not store.back_in_queue(job.id, attempt=1) and store.get(job.id).status == "running"
    runner.shutdown()


@both
def test_a_job_that_fails_or_is_cancelled_after_writing_results_leaves_none(store: JobStore, tmp_path: Path,
                                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """A failure after the results were written (the refined poses' step, a time limit) leaves no
    volume of a failed job for the retention time; a cancel that deleted the job's files while the
    run went on writing leaves nothing of what it wrote after."""
    from service.core.errors import Cancelled
    from service.jobs import worker

    def writes_then(error: Exception):  # noqa: ANN202
        def execute(store_, folder: Path, *args: object) -> None:  # noqa: ANN001
            (folder / "outputs").mkdir(parents=True, exist_ok=True)
            (folder / "outputs" / "volume.nii.gz").write_bytes(b"patient")
            if isinstance(error, Cancelled):
                store_.cancel(job_id)
                (folder / "outputs").mkdir(parents=True, exist_ok=True)      # the run writes on after the cancel
                (folder / "outputs" / "preview.png").write_bytes(b"patient")
            raise error
        return execute

    for error, status in ((ValueError("refined poses: broken"), "failed"), (Cancelled(), "cancelled")):
        job_id = store.create({}).id
        monkeypatch.setattr(worker, "_execute", writes_then(error))
        worker.run_job(store, tmp_path / "models", job_id)
        assert store.get(job_id).status == status
        assert not (store.directory(job_id) / "outputs").exists(), status


@both
def test_a_superseded_runs_failure_leaves_the_live_runs_files(store: JobStore, tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """A first run that fails after a re-delivery took the job over leaves its inputs and results to
    the run that owns them (it deleted the inputs, and the live run then failed saying the replicas
    shared no data folder)."""
    from service.jobs import worker

    job = store.create({})
    inputs = store.directory(job.id) / "inputs"
    inputs.mkdir(parents=True)
    (inputs / "stack0.npz").write_bytes(b"voxels")

    def taken_over_then_fails(store_, folder: Path, *args: object) -> None:  # noqa: ANN001
        assert store_.claim(job.id, redelivered=True) == 2                     # the re-delivery's run
        (folder / "outputs").mkdir(parents=True, exist_ok=True)
        (folder / "outputs" / "volume.nii.gz").write_bytes(b"the live run's")
        raise ValueError("the first run's late error")

    monkeypatch.setattr(worker, "_execute", taken_over_then_fails)
    worker.run_job(store, tmp_path / "models", job.id)
    now = store.get(job.id)
    assert (now.status, now.attempts) == ("running", 2)
    assert (inputs / "stack0.npz").exists() and (store.directory(job.id) / "outputs" / "volume.nii.gz").exists()


def test_retention_frees_the_files_even_where_the_database_cannot_be_written(tmp_path: Path,
                                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """On a full disk the database refuses every write: retention removes the expired jobs' files
    first (their space is what a later write needs), and their records go once it can write."""
    from service.core.errors import StoreUnavailable

    store = SqliteJobStore(tmp_path)
    job = store.create({})
    assert store.claim(job.id) and store.finish(job.id, {})
    (store.directory(job.id) / "outputs").mkdir(parents=True)
    (store.directory(job.id) / "outputs" / "volume.nii.gz").write_bytes(b"results")
    real = SqliteJobStore._db
    calls = []

    def refusing_writes(self):  # noqa: ANN001, ANN202
        calls.append(1)
        if len(calls) > 1:                                      # the SELECT reads; the DELETE cannot write
            raise StoreUnavailable("the job store's database cannot be used (database or disk is full)")
        return real(self)

    monkeypatch.setattr(SqliteJobStore, "_db", refusing_writes)
    with pytest.raises(StoreUnavailable):
        store.expire(0.0)
    assert not store.directory(job.id).exists()
    monkeypatch.undo()
    assert store.expire(0.0) == [job.id] and store.get(job.id) is None


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)
def test_the_embedded_upkeep_fails_a_submission_no_request_reads_any_more(backend: tuple,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """A job whose request could not delete it (its clean-up refused by a full disk) stayed queued,
    never handed over, until a restart, counting against the queue's limit; the upkeep fails it once
    no request of the server has said for a lease that it reads it, and leaves one that is read."""
    from service.jobs import store as store_module
    from service.jobs.runner import INTERRUPTED

    store, runner = backend
    ghost, read = store.create({}), store.create({})
    (store.directory(ghost.id) / "inputs").mkdir()
    store.hold_submission(read.id)
    runner.maintain()
    assert store.get(ghost.id).status == "queued"                    # within the lease of its making
    later = time.time() + store_module.SUBMISSION_LEASE_S + 1
    monkeypatch.setattr(store_module.time, "time", lambda: later)
    store.hold_submission(read.id)                                    # its request goes on reading it
    runner.maintain()
    assert (store.get(ghost.id).status, store.get(ghost.id).error) == ("failed", INTERRUPTED)
    assert not (store.directory(ghost.id) / "inputs").exists()
    assert store.get(read.id).status == "queued"


@pytest.mark.parametrize("queue_settings", ["embedded"], indirect=True)
def test_a_run_that_could_not_record_its_end_fails_its_job_at_once(backend: tuple) -> None:
    """A run that raised out of its worker (its store refused the failure's record) left its job
    running until the job time limit; the runner fails it when the run's future ends so, its files
    discarded, and leaves a job whose run ended cleanly alone."""
    from concurrent.futures import Future

    from service.core.errors import StoreUnavailable
    from service.jobs.local_runner import UNRECORDED

    store, runner = backend
    stuck, clean = store.create({}), store.create({})
    for job in (stuck, clean):
        assert store.claim(job.id)
    (store.directory(stuck.id) / "outputs").mkdir(parents=True)
    raised, ended = Future(), Future()
    raised.set_exception(StoreUnavailable("the job store's database cannot be used (database or disk is full)"))
    ended.set_result(None)
    runner._check(raised, runner.pool, stuck.id)
    runner._check(ended, runner.pool, clean.id)
    deadline = time.time() + 10
    while store.get(stuck.id).status == "running" and time.time() < deadline:
        time.sleep(0.05)
    assert (store.get(stuck.id).status, store.get(stuck.id).error) == ("failed", UNRECORDED)
    assert not (store.directory(stuck.id) / "outputs").exists()
    assert store.get(clean.id).status == "running"


@pytest.mark.parametrize("queue_settings", ["redis"], indirect=True)
def test_a_redelivered_job_past_its_time_limit_fails_as_timed_out(backend: tuple,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """RQ kills a work process stuck past the job time limit (in native code, deaf to its time-out
    signal) and retries the job, which would run its whole time again and end as a lost worker: a
    re-delivery whose earlier run started longer ago than the limit fails the job saying so; one
    within it runs."""
    from pathlib import Path

    from service.jobs import rq_runner
    from service.jobs.worker import TIMED_OUT

    store, runner = backend
    late, fresh = store.create({}), store.create({})
    for job in (late, fresh):
        assert store.claim(job.id) == 1
    (store.directory(late.id) / "inputs").mkdir()
    ctx = rq_runner.WorkerContext(store, Path("models"), 2, None, timeout_s=3600.0)
    assert not rq_runner.out_of_time(ctx, fresh.id)
    later = time.time() + 3601
    monkeypatch.setattr(rq_runner.time, "time", lambda: later)
    assert rq_runner.out_of_time(ctx, late.id)
    assert (store.get(late.id).status, store.get(late.id).error) == ("failed", TIMED_OUT)
    assert not (store.directory(late.id) / "inputs").exists()


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="counts open files through Linux's /proc/self/fd")
def test_the_sqlite_store_keeps_no_database_file_open_between_calls(tmp_path: Path) -> None:
    """An idle server's upkeep reads the store every few seconds and seldom collects garbage: each
    call closes its connection, so no file of the database stays open however many calls ran."""
    import gc
    import os

    def open_database_files() -> int:
        names = []
        for fd in os.listdir("/proc/self/fd"):
            try:
                names.append(os.readlink(f"/proc/self/fd/{fd}"))
            except OSError:
                continue
        return sum("jobs.sqlite3" in name for name in names)

    store = SqliteJobStore(tmp_path / "data")
    gc.disable()
    try:
        for _ in range(50):
            store.get("0" * 32)
            store.queued()
        assert open_database_files() == 0
    finally:
        gc.enable()
