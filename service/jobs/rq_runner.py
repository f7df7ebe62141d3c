"""The distributed back-end's runner: an RQ queue on Redis (why RQ: docs/deployment.md, "Running on several machines").

* The API replicas only **enqueue** (the RQ job id is the job's id) and, every
  ``queue_maintenance_s``, **maintain**: RQ's registry clean-up re-delivers the job of a worker that
  stopped heart-beating (``kill -9``, a lost machine) while its retries last, and
  :meth:`RqRunner.reconcile` fails, with a reason, each job RQ has given up.
* ``svrnet-worker`` processes (:mod:`service.jobs.worker_cli`) run :func:`execute` in a forked work
  horse per job; the job records and the progress live in :class:`~service.jobs.redis_store.RedisJobStore`.
* **Cancel** marks the record and stops the work horse at once (RQ's stop command); a stopped job is
  never retried.

Delivery is at-least-once; "run to completion once" comes from the store: a job is claimed
atomically, only ``running -> succeeded`` finishes it, and a horse whose worker died exits (it
watches its parent), so the re-delivered run is the only one left.
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import redis
from rq import Callback, Queue, Retry, get_current_job, worker_registration
from rq.command import send_stop_job_command
from rq.exceptions import InvalidJobOperation, NoSuchJobError
from rq.job import Job as RqJob
from rq.job import JobStatus
from rq.registry import clean_registries

from service.core.errors import StoreUnavailable
from service.core.process_pools import watch_parent
from service.core.settings import Settings
from service.jobs.redis_store import RedisJobStore
from service.jobs.runner import JobRunner, lost_worker
from service.jobs.store import FINAL, SUBMISSION_LEASE_S, Job
from service.jobs.worker import TIMED_OUT, run_job

log = logging.getLogger(__name__)

GIVEN_UP = (JobStatus.FAILED, JobStatus.STOPPED, JobStatus.CANCELED, JobStatus.FINISHED)
WAITING = (JobStatus.QUEUED, JobStatus.DEFERRED, JobStatus.SCHEDULED)
"""RQ's states of a job that waits for a worker: a run the store shows running is over (its worker was
lost, and the registry's clean-up put the job back) and the job is queued again."""


@dataclass
class WorkerContext:
    """What a work horse needs: set by ``svrnet-worker`` before it forks (else read from ``SVRNET_*``)."""

    store: RedisJobStore
    models_dir: Path
    max_attempts: int
    localisers_dir: Path | None = None
    timeout_s: float = float("inf")
    """The job time limit (``SVRNET_JOB_TIMEOUT_H``): a re-delivered job whose earlier run started longer
    ago has had its time."""


_context: WorkerContext | None = None


def set_context(settings: Settings) -> WorkerContext:
    global _context
    assert settings.queue_url, "the distributed back-end needs SVRNET_QUEUE_URL"
    _context = WorkerContext(RedisJobStore(settings.queue_url, settings.data_dir, settings.queue_name),
                             Path(settings.models_dir), settings.job_max_attempts, Path(settings.localisers_dir),
                             settings.job_timeout_h * 3600)
    return _context


def worker_context() -> WorkerContext:
    """This worker process's context (:func:`set_context`; from the environment's settings if unset)."""
    return _context or set_context(Settings())


def execute(job_id: str) -> None:
    """The RQ task (in the work horse): run the job; ``redelivered`` when RQ retried it."""
    ctx = worker_context()
    watch_parent()
    current = get_current_job()
    retries_left = current.retries_left if current is not None else None
    redelivered = retries_left is not None and retries_left < ctx.max_attempts - 1
    if redelivered:
        log.info(f"re-delivered job {job_id}, attempt {ctx.max_attempts - retries_left}", extra={"job_id": job_id})
        if out_of_time(ctx, job_id):
            return
    run_job(ctx.store, ctx.models_dir, job_id, redelivered=redelivered, localisers_dir=ctx.localisers_dir)
    if current is not None:
        drop_waiting_redelivery(ctx, current)


def drop_waiting_redelivery(ctx: WorkerContext, current: RqJob) -> None:
    """Take out of the queue a re-delivery of ``current`` that waits there although its job has ended:
    RQ put the job back when it took this run for lost (its worker silent too long), and the run
    lived on and ended the job (:meth:`~service.jobs.redis_store.RedisJobStore.finish` accepts a job
    put back under its run). The re-delivery would only find the job ended, after taking a worker;
    where the store or the queue does not answer it is left to do so."""
    try:
        job = ctx.store.get(current.id)
        if job is not None and job.status in FINAL:
            Queue(current.origin, connection=current.connection).remove(current.id)
    except (StoreUnavailable, redis.RedisError):
        log.warning("a re-delivery of an ended job may wait in the queue", extra={"job_id": current.id})


def out_of_time(ctx: WorkerContext, job_id: str) -> bool:
    """Fail a re-delivered job whose earlier run started longer ago than the job time limit (RQ kills a
    work process that cannot take its time-out signal, stuck in native code, a minute past the limit,
    and retries it: the job would run its whole time again), saying so; whether it did."""
    job = ctx.store.get(job_id)
    if job is None or job.status != "running" or not job.ran_longer_than(ctx.timeout_s):
        return False
    ctx.store.give_up(job_id, TIMED_OUT, job.attempts)
    return True


def on_stopped(job: RqJob, connection: redis.Redis) -> None:  # noqa: ARG001 - RQ's callback signature
    """After RQ killed a cancelled job's horse (in the worker): remove what it may have written since."""
    store = worker_context().store
    if store.is_cancelled(job.id):
        shutil.rmtree(store.directory(job.id), ignore_errors=True)


def failure_reason(status: str, exc_string: str, max_attempts: int) -> str:
    """Why RQ gave the job up (its status and the last run's exception text), in words with no server
    detail.

    Example:
        >>> failure_reason("failed", "Moved to FailedJobRegistry, due to AbandonedJobError", 2)
        'the worker running it was lost 2 times (SVRNET_JOB_MAX_ATTEMPTS); the job was not completed'
        >>> failure_reason("failed", "rq.timeouts.JobTimeoutException: Task exceeded maximum timeout", 2)
        'the job ran longer than SVRNET_JOB_TIMEOUT_H and was stopped'
    """
    if "JobTimeoutException" in exc_string:
        return TIMED_OUT
    if status == JobStatus.FINISHED:
        return "the worker ended without completing the job"
    return lost_worker(max_attempts)


class RqRunner(JobRunner):
    """Enqueues jobs on the RQ queue ``settings.queue_name``; the workers are ``svrnet-worker`` processes."""

    submit_grace_s = 2 * SUBMISSION_LEASE_S
    """A job created this long ago, never handed to the queue and whose submission no replica holds
    (:meth:`~service.jobs.store.JobStore.submission_held`), was orphaned by a replica that stopped."""

    def __init__(self, store: RedisJobStore, settings: Settings) -> None:
        self.store, self.settings = store, settings
        self.connection = redis.Redis.from_url(settings.queue_url, socket_timeout=10, socket_connect_timeout=5)
        self.queue = Queue(settings.queue_name, connection=self.connection)

    def start(self) -> list[str]:
        try:
            self.maintain()
        except redis.RedisError:
            log.warning("the queue is not reachable yet; /readyz says so until it is")
        return []

    def submit(self, job_id: str) -> None:
        """Enqueue ``job_id``; :class:`~service.core.errors.StoreUnavailable` (503) where Redis does not
        answer (the caller then deletes the job, which no worker will run)."""
        handed = time.time()
        retries = self.settings.job_max_attempts - 1
        try:
            self.queue.enqueue(execute, job_id, job_id=job_id, retry=Retry(max=retries) if retries else None,
                               job_timeout=int(self.settings.job_timeout_h * 3600), result_ttl=600,
                               failure_ttl=int(self.settings.retention_hours * 3600), on_stopped=Callback(on_stopped),
                               description="svrnet reconstruction")
        except redis.RedisError as exc:
            raise StoreUnavailable("the job queue (Redis) does not answer; retry later", 5) from exc
        self.store.update(job_id, submitted_at=handed)

    def cancel(self, job_id: str) -> None:
        try:
            rq_job = RqJob.fetch(job_id, connection=self.connection)
            if rq_job.get_status() == JobStatus.STARTED:
                send_stop_job_command(self.connection, job_id)
            else:
                # Off the queue and gone: RQ's registry of cancelled jobs is never cleaned, and its
                # record of the job would otherwise stay in Redis for good.
                rq_job.delete(remove_from_queue=True)
        except (NoSuchJobError, InvalidJobOperation):
            pass                       # already over: the store's state is what counts

    def maintain(self) -> None:
        if self.queue.acquire_maintenance_lock():
            try:
                clean_registries(self.queue)
                worker_registration.clean_worker_registry(self.queue)   # names of workers long gone
            finally:
                self.queue.release_maintenance_lock()
        self.reconcile()

    def reconcile(self) -> list[str]:
        """Fail (with the reason) every unfinished job RQ has given up or lost, or whose submission a
        stopped replica left half done (their ids); show as queued again a job whose run RQ put back
        in the queue after its worker was lost (:data:`WAITING`), or fail it as timed out where that
        run started longer ago than the job time limit (:meth:`_past_time_limit`)."""
        failed = []
        for job_id in self.store.ids("queued") + self.store.ids("running"):
            job = self.store.get(job_id)
            if job is None:
                continue
            if job.submitted_at is None:   # being stored by a replica, or orphaned when it stopped
                if self.store.fail_abandoned(job, self.submit_grace_s):
                    failed.append(job_id)
                continue
            try:
                rq_job = RqJob.fetch(job_id, connection=self.connection)
                status = rq_job.get_status(refresh=True)
                waiting = job.status == "running" and status in WAITING
                if waiting and self._past_time_limit(job):     # its waiting re-delivery finds it ended
                    gone, reason = True, TIMED_OUT
                elif waiting and self.store.back_in_queue(job_id, job.attempts):
                    log.warning(f"job {job_id} is queued again: its worker was lost", extra={"job_id": job_id})
                    continue
                else:
                    gone = status in GIVEN_UP and not self._finished_under_a_live_run(job, status)
                    last = rq_job.latest_result() if gone else None
                    reason = failure_reason(status, (last.exc_string if last else None) or "",
                                            self.settings.job_max_attempts) if gone else ""
            except NoSuchJobError:     # or a superseded run's `finished` record that expired under the live run
                gone = not (job.attempts > 1 and self._within_a_live_run(job))
                reason = "the queue lost the job (was Redis restarted without persistence?)"
            if gone and self.store.give_up(job_id, reason, job.attempts):   # not a later run's claim
                failed.append(job_id)
        return failed

    def _past_time_limit(self, job: Job) -> bool:
        """Whether the run of ``job`` that RQ put back in the queue (its worker fell silent, or RQ killed
        its work horse past the limit) started longer ago than the job time limit: its re-delivery
        would run the job's whole time again. The re-delivery's own check (:func:`out_of_time`)
        acts on a job the store shows running, and the reconcile that shows it queued again would
        hide it from that check, so the reconcile judges the time itself while the store still
        holds the run's start. A job queued otherwise (handed back by a stopping worker, its
        earlier start kept) is never judged so: the store shows it queued, not running."""
        return job.ran_longer_than(self.settings.job_timeout_h * 3600)

    def _finished_under_a_live_run(self, job: Job, status: str) -> bool:
        """Whether RQ's ``finished`` is a superseded run's while a later run may still be running the
        job (then the job is not given up).

        A job's task returns without ending the job only where another run took it over (RQ
        re-delivered it after its worker had been silent too long, and the first run, alive after
        all, stopped at its next stage): that return marks the shared RQ job ``finished`` under the
        run in progress. The job is given up only once that run could no longer be alive (the job
        time limit and a lost worker's silence past its latest start)."""
        return status == JobStatus.FINISHED and self._within_a_live_run(job)

    def _within_a_live_run(self, job: Job) -> bool:
        """Whether a run of the running ``job`` may still be alive: its latest start lies within the
        job time limit and a lost worker's silence. The superseded run's ``finished`` record expires
        (``result_ttl``) long before that, so a re-delivered job whose RQ record is gone is given
        up on the same clock."""
        limit = self.settings.job_timeout_h * 3600 + self.settings.worker_lost_after_s + self.settings.worker_heartbeat_s
        return job.status == "running" and time.time() - (job.started_at or job.updated_at) < limit

    def stats(self) -> dict[str, float]:
        return {"workers": float(self._alive_workers()), "queue_length": float(len(self.queue))}

    def live_workers(self) -> int | None:
        try:
            return self._alive_workers()
        except redis.RedisError:
            return None

    def _alive_workers(self) -> int:
        """The ``svrnet-worker`` processes serving the queue: those registered on it whose record is
        alive (a worker's record expires once its heartbeat has stopped for its time to live, after a
        ``kill -9`` or a lost machine; its name stays registered until the next clean-up)."""
        keys = list(worker_registration.get_keys(queue=self.queue))
        with self.connection.pipeline() as pipeline:
            for key in keys:
                pipeline.exists(key)
            return sum(bool(alive) for alive in pipeline.execute())

    def shutdown(self) -> list[str]:
        self.connection.close()
        return []
