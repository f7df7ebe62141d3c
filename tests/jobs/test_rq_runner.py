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
