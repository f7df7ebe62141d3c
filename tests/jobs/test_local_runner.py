"""One server owns an embedded job store: a second one on the same folder is refused before it
touches the first one's running jobs; the lock dies with its owner, ``kill -9`` included."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from service.jobs.local_runner import LOCK_NAME, LocalRunner, StoreInUse
from service.jobs.sqlite_store import SqliteJobStore

ROOT = Path(__file__).resolve().parents[2]

HOLD = """
import sys, time
from pathlib import Path
from service.jobs.local_runner import LocalRunner
from service.jobs.sqlite_store import SqliteJobStore
runner = LocalRunner(SqliteJobStore(Path(sys.argv[1])), Path(sys.argv[1]))
runner.start()
print("owner", flush=True)
time.sleep(600)
"""


def test_a_second_server_on_the_store_is_refused_and_leaves_the_running_job_alone(tmp_path: Path) -> None:
    store = SqliteJobStore(tmp_path)
    first = LocalRunner(store, tmp_path)
    first.start()
    job = store.create({"model": "default"})
    assert store.claim(job.id) == 1                                       # the first server runs it
    with pytest.raises(StoreInUse, match=rf"{tmp_path}.*another running svrnet-server \(pid \d+\).*SVRNET_DATA_DIR"):
        LocalRunner(SqliteJobStore(tmp_path), tmp_path).start()
    assert store.get(job.id).status == "running"                         # not queued again under it
    first.shutdown()
    second = LocalRunner(SqliteJobStore(tmp_path), tmp_path)
    assert second.start() == [job.id]                                   # handed back by the first, taken now
    second.shutdown()


def test_the_lock_dies_with_its_owner(tmp_path: Path) -> None:
    owner = subprocess.Popen([sys.executable, "-c", HOLD, str(tmp_path)], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert owner.stdout.readline().strip() == "owner"
        assert (tmp_path / LOCK_NAME).read_text() == str(owner.pid)
        with pytest.raises(StoreInUse, match=str(owner.pid)):
            LocalRunner(SqliteJobStore(tmp_path), tmp_path).start()
    finally:
        owner.send_signal(signal.SIGKILL)
        owner.wait(30)
    runner = LocalRunner(SqliteJobStore(tmp_path), tmp_path)
    runner.start()                                                        # no stale lock after kill -9
    runner.shutdown()


def test_a_job_worker_runs_the_servers_blas_threads(tmp_path: Path) -> None:
    from service.core.threads import blas_threads

    runner = LocalRunner(SqliteJobStore(tmp_path), tmp_path, blas_threads=1)
    try:
        assert set(runner.pool.submit(blas_threads).result(timeout=120)) == {1}
    finally:
        runner.pool.shutdown(wait=True, cancel_futures=True)


def test_workers_stopped_after_their_job_ended_on_its_own_are_replaced(tmp_path: Path,
                                                                        caplog: pytest.LogCaptureFixture) -> None:
    # A cancelled job can see its cancel at a stage's end and return before the runner kills its
    # worker: the idle worker's death fails no future, so the runner must replace the pool itself.
    import os
    import time

    runner = LocalRunner(SqliteJobStore(tmp_path), tmp_path)
    broken = runner.pool
    try:
        worker_pid = broken.submit(os.getpid).result(timeout=120)          # a live, idle worker
        with caplog.at_level("INFO", logger="service.jobs.local_runner"):
            runner._stop_workers("a cancelled job")
            deadline = time.time() + 30                 # the log line comes last, after the new pool and the recovery
            while "job workers stopped for a cancelled job and replaced" not in caplog.text:
                assert time.time() < deadline
                time.sleep(0.05)
        assert runner.pool is not broken and runner.stopped_for is None
        assert runner.pool.submit(os.getpid).result(timeout=120) != worker_pid   # the new pool runs jobs
    finally:
        runner.shutdown()


def test_a_replaced_pool_leaves_a_job_still_being_uploaded_to_its_request(tmp_path: Path) -> None:
    # A job is stored (queued) before its uploads are written; the request submits it once they
    # are. A pool replaced meanwhile (another job cancelled, timed out, or its worker lost) must not
    # hand it to a worker, which would fail it for missing uploads while they are being written.
    store = SqliteJobStore(tmp_path)
    runner = LocalRunner(store, tmp_path)
    try:
        uploading = store.create({"model": "default"})
        runner._replace(runner.pool)
        assert uploading.id not in runner.futures
        assert store.get(uploading.id).status == "queued" and store.get(uploading.id).submitted_at is None
    finally:
        runner.shutdown()


def test_at_start_a_job_whose_upload_was_cut_short_fails_saying_so_and_a_complete_one_runs(tmp_path: Path) -> None:
    from service.jobs.runner import INTERRUPTED

    store = SqliteJobStore(tmp_path)
    cut_short, complete = store.create({"model": "default"}), store.create({"model": "default"})
    for job in (cut_short, complete):
        (store.directory(job.id) / "inputs").mkdir(parents=True)
        (store.directory(job.id) / "inputs" / "stack0").write_bytes(b"Doe")
    (store.directory(complete.id) / "inputs" / "params.json").write_text("{}")     # written last, before submit
    runner = LocalRunner(store, tmp_path)
    try:
        assert runner.start() == [complete.id]
        assert store.get(cut_short.id).status == "failed" and store.get(cut_short.id).error == INTERRUPTED
        assert not (store.directory(cut_short.id) / "inputs").exists()
    finally:
        runner.shutdown()


def test_a_job_running_beside_a_timed_out_one_runs_again_without_losing_an_attempt(tmp_path: Path) -> None:
    # A pool's processes stop together: the timed-out job's stop takes its neighbour's process too.
    import time

    from service.jobs.worker import TIMED_OUT

    store = SqliteJobStore(tmp_path)
    runner = LocalRunner(store, tmp_path, max_attempts=1, timeout_s=60.0)
    try:
        late, beside = store.create({}), store.create({})
        for job in (late, beside):
            assert store.claim(job.id) == 1
            runner.futures[job.id] = runner.pool.submit(time.sleep, 30)    # what the pool's processes run
        with store._db() as db:
            db.execute("UPDATE jobs SET started_at = ? WHERE id = ?", (time.time() - 120, late.id))
        resubmitted: list[str] = []
        runner.submit = resubmitted.append                                  # the new pool is not needed here
        runner.maintain()
        deadline = time.time() + 60
        while not resubmitted:                                              # recovered once the processes are gone
            assert time.time() < deadline
            time.sleep(0.05)
        assert resubmitted == [beside.id]
        assert store.get(late.id).status == "failed" and store.get(late.id).error == TIMED_OUT
        again = store.get(beside.id)
        assert again.status == "queued" and again.attempts == 0, again      # at max_attempts 1 it would have failed
    finally:
        runner.shutdown()


def test_a_timed_out_job_keeps_neither_its_uploads_nor_what_it_wrote_of_its_results(tmp_path: Path) -> None:
    """The time limit fails the job and stops its run: what the run had written of its results (a
    volume, before the poses' step) is never served, so it goes with the uploads, not at the
    retention limit."""
    import time

    store = SqliteJobStore(tmp_path)
    runner = LocalRunner(store, tmp_path, max_attempts=1, timeout_s=60.0)
    try:
        late = store.create({})
        assert store.claim(late.id) == 1
        for part, name in (("inputs", "stack0"), ("outputs", "volume.nii.gz")):
            (store.directory(late.id) / part).mkdir()
            (store.directory(late.id) / part / name).write_bytes(b"Doe^Jane")
        with store._db() as db:
            db.execute("UPDATE jobs SET started_at = ? WHERE id = ?", (time.time() - 120, late.id))
        runner.maintain()
        assert store.get(late.id).status == "failed"
        assert not [p for p in store.directory(late.id).rglob("*") if p.is_file()]
    finally:
        runner.shutdown()


def test_an_orderly_stop_hands_running_jobs_back_without_spending_an_attempt(tmp_path: Path) -> None:
    """Two rolling restarts at ``max_attempts`` 1 leave the job queued; a server killed outright
    (the next start's recovery, without a shutdown) still counts."""
    import time

    store = SqliteJobStore(tmp_path)
    job = store.create({})
    for _ in range(2):
        runner = LocalRunner(store, tmp_path, max_attempts=1)
        runner.started = True
        assert store.claim(job.id) == 1
        runner.futures[job.id] = runner.pool.submit(time.sleep, 30)
        assert runner.shutdown(timeout_s=5.0) == [job.id]
        again = store.get(job.id)
        assert again.status == "queued" and again.attempts == 0, again
    assert store.claim(job.id) == 1
    store.recover(max_attempts=1)                                    # a start after a kill -9
    assert store.get(job.id).status == "failed"


def test_a_stop_hands_back_and_logs_only_the_jobs_that_had_started(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Jobs submitted to the pool but still waiting there are not "handed back": they never left the queue."""
    from concurrent.futures import Future

    store = SqliteJobStore(tmp_path)
    runner = LocalRunner(store, tmp_path)
    runner.start()
    started, waiting = store.create({}), store.create({})
    assert store.claim(started.id) == 1
    runner.futures = {started.id: Future(), waiting.id: Future()}       # both in the pool, one taken by a worker
    with caplog.at_level("INFO", logger="service"):
        assert runner.shutdown() == [started.id]
    assert [r.job_id for r in caplog.records if r.getMessage() == "handed a job back to the queue"] == [started.id]
    assert [store.get(j.id).status for j in (started, waiting)] == ["queued", "queued"]
    assert store.get(started.id).attempts == 0                           # an orderly stop spends no attempt


@pytest.mark.parametrize("disk_freed", ["while_retried", "after_the_retries"])
def test_a_run_whose_end_the_store_refused_twice_fails_once_the_store_writes_again(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, disk_freed: str) -> None:
    """A run raised out of its worker (the full disk refused its failure's record) and the runner's
    immediate try is refused too: once the store writes again the job fails, its files discarded (it
    showed running, run by no process, until the job time limit): within seconds while the runner
    tries again, else at the next upkeep. A job running in the pool, and one whose run is not known
    to have ended (its pool being replaced), stay running."""
    import threading
    from concurrent.futures import Future

    from service.core.errors import StoreUnavailable
    from service.jobs import local_runner
    from service.jobs.local_runner import UNRECORDED

    monkeypatch.setattr(local_runner, "UNRECORDED_RETRY_S", 0.05)
    if disk_freed == "after_the_retries":
        monkeypatch.setattr(local_runner, "UNRECORDED_RETRY_FOR_S", 0.0)
    store = SqliteJobStore(tmp_path)
    runner = LocalRunner(store, tmp_path, timeout_s=3600.0)
    try:
        stuck, beside, recovering = store.create({}), store.create({}), store.create({})
        for job in (stuck, beside, recovering):
            assert store.claim(job.id) == 1
        (store.directory(stuck.id) / "outputs").mkdir()
        runner.futures[beside.id] = Future()                                # its run goes on in the pool
        full = StoreUnavailable("the job store's database cannot be used (database or disk is full)")
        real_fail = SqliteJobStore.fail
        room = threading.Event()
        tries: list[float] = []

        def refused_while_full(self: SqliteJobStore, *args: object, **kwargs: object) -> bool:
            tries.append(time.monotonic())
            if not room.is_set():
                raise full
            return real_fail(self, *args, **kwargs)

        monkeypatch.setattr(SqliteJobStore, "fail", refused_while_full)
        raised = Future()
        raised.set_exception(full)
        runner._check(raised, runner.pool, stuck.id)
        [ender] = [t for t in threading.enumerate() if t.name == "job-end"]
        time.sleep(0.3)
        assert store.get(stuck.id).status == "running"
        room.set()                                                          # the disk has room again
        ender.join(10)
        assert not ender.is_alive()
        if disk_freed == "while_retried":
            assert len(tries) > 2                                           # tried again without the upkeep
        else:
            assert len(tries) == 1 and store.get(stuck.id).status == "running"
            runner.maintain()
        assert (store.get(stuck.id).status, store.get(stuck.id).error) == ("failed", UNRECORDED)
        assert not (store.directory(stuck.id) / "outputs").exists() and runner.unrecorded == {}
        assert store.get(beside.id).status == "running" and store.get(recovering.id).status == "running"
    finally:
        runner.shutdown()


def test_cancelling_a_waiting_job_then_the_running_one_leaves_the_pools_clean_up_whole(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # One worker runs R; B waits in the pool's call queue and W behind it. W is cancelled, then R,
    # which runs alone: its worker is killed. The broken pool's management thread sets an error on
    # every waiting future; a future the runner had cancelled raised InvalidStateError there, the
    # thread died part-way and the broken pool's clean-up was skipped.
    import threading

    died: list[BaseException] = []
    monkeypatch.setattr(threading, "excepthook", lambda args: died.append(args.exc_value))
    store = SqliteJobStore(tmp_path)
    runner = LocalRunner(store, tmp_path, workers=1)
    try:
        running, behind, waiting = store.create({}), store.create({}), store.create({})
        assert store.claim(running.id) == 1
        for job in (running, behind, waiting):
            runner.futures[job.id] = runner.pool.submit(time.sleep, 30)     # what the pool's processes run
        runner.submit = lambda job_id: None                                 # the new pool is not needed here
        broken = runner.pool
        for job in (waiting, running):                                      # as DELETE does
            assert store.cancel(job.id)
            runner.cancel(job.id)
        deadline = time.time() + 60
        while runner.pool is broken:                                        # replaced once the worker is gone
            assert time.time() < deadline
            time.sleep(0.05)
        time.sleep(0.5)                                                     # the broken pool's thread ends
        assert not died, died
        assert store.get(waiting.id).status == "cancelled" and store.get(behind.id).status == "queued"
    finally:
        runner.shutdown()
