"""The distributed back-end's runner on a real Redis: what a replica's upkeep (:meth:`RqRunner.reconcile`)
does with a job whose run RQ put back in the queue, and what a work horse's task does once its run
has ended."""

from __future__ import annotations

import time

import pytest
from rq.job import Job as RqJob
from rq.job import JobStatus

from service.jobs import rq_runner

redis_only = pytest.mark.parametrize("queue_settings", ["redis"], indirect=True)


@redis_only
def test_a_job_rq_put_back_past_its_time_limit_fails_as_timed_out(backend: tuple,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """RQ re-queues a run whose work horse it killed past the job time limit (or whose worker fell
    silent): where that run started longer ago than the limit, the reconcile fails the job as timed
    out (its re-delivery would otherwise run its whole time again); within the limit it shows the job
    queued again; a job handed back by a stopping worker (queued, its earlier start kept) stays
    queued."""
    from service.jobs.worker import TIMED_OUT

    store, runner = backend
    late, lost, handed = store.create({}), store.create({}), store.create({})
    for job in (late, lost, handed):
        (store.directory(job.id) / "inputs").mkdir()
        runner.submit(job.id)
        assert store.claim(job.id) == 1
    assert store.hand_back(handed.id)
    limit = runner.settings.job_timeout_h * 3600
    with store.redis.pipeline() as pipe:                                 # `late` started before the limit
        pipe.hset(store._key(late.id), "started_at", repr(time.time() - limit - 120))
        pipe.hset(store._key(handed.id), "started_at", repr(time.time() - limit - 120))
        pipe.execute()
    for job in (late, lost):
        RqJob.fetch(job.id, connection=runner.connection).set_status(JobStatus.QUEUED)    # RQ's retry, waiting
    assert runner.reconcile() == [late.id]
    assert (store.get(late.id).status, store.get(late.id).error) == ("failed", TIMED_OUT)
    assert not (store.directory(late.id) / "inputs").exists()
    assert store.get(lost.id).status == "queued" and "worker was lost" in store.get(lost.id).stage
    assert store.get(handed.id).status == "queued" and store.get(handed.id).attempts == 0
    ctx = rq_runner.WorkerContext(store, store.data_dir / "models", 2, None, timeout_s=limit)
    assert not rq_runner.out_of_time(ctx, late.id)                      # ended: its re-delivery does not run it
    assert store.claim(late.id, redelivered=True) == 0


@redis_only
def test_a_run_taken_for_lost_that_completes_its_job_keeps_its_results(backend: tuple,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """RQ takes a live run for lost (its worker silent too long) and puts the job back in the queue,
    which the reconcile shows queued; the run lives on and completes: the job succeeds with its
    results (not thrown away and computed again), and the waiting re-delivery leaves the queue."""
    from service.jobs import worker

    store, runner = backend
    job = store.create({})
    (store.directory(job.id) / "inputs").mkdir()
    runner.submit(job.id)                                # its id in the queue: the re-delivery, once RQ puts it back

    def completes_after_being_taken_for_lost(store_, folder, models_dir, job_id, progress, attempt,  # noqa: ANN001
                                             *args: object) -> None:
        RqJob.fetch(job_id, connection=runner.connection).set_status(JobStatus.QUEUED)    # RQ's clean-up
        assert runner.reconcile() == [] and store_.get(job_id).status == "queued"
        (folder / "outputs").mkdir()
        (folder / "outputs" / "volume.nii.gz").write_bytes(b"hours of work")
        if not store_.finish(job_id, {"slices": [1]}, attempt):                           # as _execute ends
            raise worker.Superseded

    monkeypatch.setattr(worker, "_execute", completes_after_being_taken_for_lost)
    monkeypatch.setattr(rq_runner, "watch_parent", lambda: None)                          # not a work horse
    monkeypatch.setattr(rq_runner, "get_current_job", lambda: RqJob.fetch(job.id, connection=runner.connection))
    monkeypatch.setattr(rq_runner, "_context", rq_runner.WorkerContext(
        store, store.data_dir / "models", runner.settings.job_max_attempts))
    assert runner.queue.job_ids == [job.id]
    rq_runner.execute(job.id)
    done = store.get(job.id)
    assert (done.status, done.attempts, done.report) == ("succeeded", 1, {"slices": [1]})
    assert (store.directory(job.id) / "outputs" / "volume.nii.gz").read_bytes() == b"hours of work"
    assert runner.queue.job_ids == []
