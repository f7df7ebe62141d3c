"""The embedded back-end's runner: a pool of worker processes beside the API.

Jobs are recovered at start (interrupted ones re-queued, see
:meth:`~service.jobs.sqlite_store.SqliteJobStore.recover`); on shutdown the workers are stopped and their
running jobs handed back to the queue, to be re-run after a restart (as after ``kill -9``).

A worker process that dies under a job (the kernel's out-of-memory killer, a signal) breaks its
pool for good: every job of it fails with ``BrokenProcessPool``, and so would every later
submission. The runner then starts a new pool and recovers the jobs as after a restart, with the
lost worker as the cause: the interrupted ones run again up to ``max_attempts`` times, then fail
saying so, and the queued ones run. A job running longer than ``timeout_s`` is failed saying so and
stopped the same way (:meth:`LocalRunner.maintain`): a job stops only with its process, and a pool's
processes stop together, so the jobs running beside it run again without losing an attempt. So does a
running job cancelled while no other job runs in the pool (:meth:`LocalRunner.cancel`); beside
others it stops at its next stage, so that theirs go on.

One server owns a job store: :meth:`LocalRunner.start` locks the store's folder
(:data:`LOCK_NAME`, an OS lock that dies with its process, ``kill -9`` included) and refuses to start
where another server holds it. Without the lock a second server's start (another port, ``make serve``
in a second terminal, a test run) would take the first one's running jobs for interrupted ones and
queue them again under it. Several servers share jobs through the distributed back-end.
"""

from __future__ import annotations

import logging
import multiprocessing
import multiprocessing.connection
import os
import sys
import threading
import time
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import IO

from service.core.errors import StoreUnavailable
from service.core.process_pools import end_pool, release_memory
from service.jobs.runner import INTERRUPTED, JobRunner, start_worker
from service.jobs.sqlite_store import SqliteJobStore
from service.jobs.store import SUBMISSION_LEASE_S, Job
from service.jobs.worker import TIMED_OUT, run_job

log = logging.getLogger(__name__)

LOCK_NAME = "server.lock"
UNRECORDED_RETRY_S = 5.0
"""How often a job whose end the store refused is tried again (:meth:`LocalRunner._fail_unrecorded`):
a full disk is usually freed within minutes, and the job should not show ``running`` much longer."""
UNRECORDED_RETRY_FOR_S = 600.0
"""How long it is tried so; after that the job upkeep tries (:meth:`LocalRunner.maintain`)."""
"""The file in the store's folder whose lock says which server owns the store (its pid inside)."""


class StoreInUse(RuntimeError):
    """Another live server owns the job store."""


def lock_store(data_dir: Path) -> IO[str] | None:
    """Lock ``data_dir`` for this process (:class:`StoreInUse`, naming the owner's pid, where another
    process holds it); the returned file keeps the lock until it is closed or the process ends."""
    if sys.platform == "win32":
        return None
    import fcntl

    data_dir.mkdir(parents=True, exist_ok=True)
    handle = open(data_dir / LOCK_NAME, "a+")          # noqa: SIM115 - held for the server's life
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        owner = handle.read().strip() or "unknown"
        handle.close()
        raise StoreInUse(f"the job store {data_dir} belongs to another running svrnet-server (pid {owner}); give "
                         "this server its own SVRNET_DATA_DIR, or run several servers on the distributed back-end "
                         "(SVRNET_QUEUE_URL)") from None
    except OSError as exc:                             # a file system without locks (some network mounts)
        handle.close()
        log.warning(f"the job store's folder cannot be locked ({exc.strerror}); run one server on it")
        return None
    handle.seek(0)
    handle.truncate()
    handle.write(str(os.getpid()))
    handle.flush()
    return handle


def _run(data_dir: str, models_dir: str, job_id: str, localisers_dir: str | None = None) -> None:
    """What a pool process executes: the job, then its memory handed back (the process waits for the
    next job)."""
    try:
        run_job(SqliteJobStore(Path(data_dir)), Path(models_dir), job_id,
                localisers_dir=None if localisers_dir is None else Path(localisers_dir))
    finally:
        release_memory()


UNRECORDED = "the job's worker could not record how the job ended (the job store refused its write)"
"""A job's failure where its run raised instead of recording its end."""


class LocalRunner(JobRunner):
    """Submits queued jobs to a pool of ``workers`` processes (spawned, each exits with the server)."""

    def __init__(self, store: SqliteJobStore, models_dir: Path, workers: int = 1, max_attempts: int = 2,
                 log_level: str = "info", timeout_s: float = float("inf"), blas_threads: int = 1,
                 localisers_dir: Path | None = None) -> None:
        self.store, self.models_dir, self.max_attempts, self.workers = store, models_dir, max_attempts, workers
        self.localisers_dir = localisers_dir
        self.log_level, self.timeout_s, self.blas_threads = log_level, timeout_s, blas_threads
        self.lock = threading.Lock()
        self.closing = threading.Event()
        """Set at shutdown: the workers stopped then are not lost ones, no pool replaces theirs, and the
        threads that wait to try a write again stop waiting."""
        self.stopping = threading.Lock()
        """Held while the runner stops: one stop at a time."""
        self.pool = self._new_pool()
        self.futures: dict[str, Future] = {}
        self.stopped_for: str | None = None
        """Why the runner itself stopped the pool's processes (a timed-out or cancelled job), for the log."""
        self.spared: list[str] = []
        """The jobs running beside the one the runner stopped the pool for: their run does not count."""
        self.unrecorded: dict[str, str] = {}
        """The jobs whose run raised out of :func:`~service.jobs.worker.run_job` (its record of the end
        refused) and that are not failed yet, with the run's kind of error: :meth:`maintain` tries again."""
        self.owner = None
        """The store's lock file while this runner owns the store (:func:`lock_store`)."""
        self.started = False
        """Whether :meth:`start` took the store (only then does :meth:`shutdown` hand jobs back)."""

    def _new_pool(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=start_worker, initargs=(os.getpid(), self.log_level, self.blas_threads))

    def start(self) -> list[str]:
        self.owner = lock_store(self.store.data_dir)
        self.started = True
        lost = set(self.store.ids("running"))      # runs a stop did not hand back (kill -9, a crash)
        queued = self._handed_over(self.store.recover(self.max_attempts), fail_others=True)
        for job in queued:
            if job.id in lost:
                log.info(f"re-queued job {job.id}, attempt {job.attempts + 1}",
                         extra={"job_id": job.id, "attempt": job.attempts + 1})
            elif job.started_at is not None:       # it ran before, and a stop handed it back
                log.info(f"resumed job {job.id} (stopped at the last shutdown; the run did not count)",
                         extra={"job_id": job.id, "attempt": job.attempts + 1})
            self.submit(job.id)
        return [job.id for job in queued]

    def submit(self, job_id: str) -> None:
        self.store.update(job_id, submitted_at=time.time())
        with self.lock:
            if self.closing.is_set():          # the server is stopping: the job waits, queued, for its next start
                log.info("job queued for the next start", extra={"job_id": job_id})
                return
            try:
                future = self.pool.submit(_run, str(self.store.data_dir), str(self.models_dir), job_id,
                                          None if self.localisers_dir is None else str(self.localisers_dir))
            except BrokenProcessPool:          # broken since the last job ended: recovered below
                future = None
            pool = self.pool
            if future is not None:
                self.futures[job_id] = future
        if future is None:
            self._replace(pool)
        else:
            future.add_done_callback(lambda f: self._check(f, pool, job_id))

    def _check(self, future: Future, pool: ProcessPoolExecutor, job_id: str) -> None:
        """A job's future ended: forget it; if its pool broke, replace it (in a thread of its own: this
        callback runs in the broken pool's own management thread)."""
        with self.lock:
            if self.futures.get(job_id) is future:
                del self.futures[job_id]
        error = None if future.cancelled() else future.exception()
        if isinstance(error, BrokenProcessPool):
            threading.Thread(target=self._replace, args=(pool,), name="job-pool-recovery", daemon=True).start()
        elif error is not None:        # the run could not record its own end (the store refused its write)
            with self.lock:
                self.unrecorded[job_id] = type(error).__name__
            threading.Thread(target=self._fail_unrecorded, args=(job_id,), name="job-end", daemon=True).start()

    def _fail_unrecorded(self, job_id: str) -> None:
        """:meth:`_give_up_unrecorded` at once, and while the store refuses that write too (the full
        disk that refused the run's) again every :data:`UNRECORDED_RETRY_S` for
        :data:`UNRECORDED_RETRY_FOR_S`, until the runner closes; then :meth:`maintain` tries."""
        deadline = time.monotonic() + UNRECORDED_RETRY_FOR_S
        warned = False
        while True:
            try:
                self._give_up_unrecorded(job_id)
                return
            except StoreUnavailable:
                if not warned:
                    log.warning("a job's end could not be recorded; it is tried again", extra={"job_id": job_id})
                    warned = True
            if self.closing.wait(UNRECORDED_RETRY_S) or time.monotonic() > deadline:
                return

    def _give_up_unrecorded(self, job_id: str) -> None:
        """Fail the job whose run raised out of :func:`~service.jobs.worker.run_job` (:attr:`unrecorded`),
        its files discarded: it would show ``running``, run by no process, until the job time limit,
        whose stop takes the jobs beside it. Only while the store still shows it running and no run
        of it is in this runner's pool (a later run's claim takes a new attempt, which
        :meth:`~service.jobs.store.JobStore.give_up` refuses to fail); :class:`StoreUnavailable` where
        the store refuses the write, the job kept for the next try."""
        error_type = self.unrecorded.get(job_id)
        job = self.store.get(job_id)
        if (job is not None and job.status == "running" and job_id not in self.futures
                and self.store.give_up(job_id, UNRECORDED, job.attempts)):
            log.info("the run's error", extra={"job_id": job_id, "error_type": error_type})
        with self.lock:
            self.unrecorded.pop(job_id, None)

    def _replace(self, broken: ProcessPoolExecutor) -> None:
        """Start a new pool in place of ``broken`` (once, whichever job noticed first) and recover its
        jobs (the module)."""
        with self.lock:
            if self.pool is not broken or self.closing.is_set():
                return
            self.pool = self._new_pool()
            broken.shutdown(wait=False, cancel_futures=True)
            stopped_for, self.stopped_for = self.stopped_for, None
            spared, self.spared = self.spared, []
        interrupted = set(self.store.ids("running")) - set(spared)     # the runs the lost workers held
        queued = self._handed_over(self.store.recover(self.max_attempts, cause="lost worker", spared=spared))
        if stopped_for is None:
            log.warning(f"a job worker process was lost (killed, or out of memory); {len(queued)} job(s) queued again")
        else:
            log.info(f"job workers stopped for {stopped_for} and replaced; {len(queued)} job(s) queued again")
        for job in queued:
            if job.id in spared:
                log.info(f"resumed job {job.id} (its worker stopped for {stopped_for}; the run did not count)",
                         extra={"job_id": job.id, "attempt": job.attempts + 1})
            elif job.id in interrupted:
                log.info(f"re-queued job {job.id}, attempt {job.attempts + 1}",
                         extra={"job_id": job.id, "attempt": job.attempts + 1})
            self.submit(job.id)

    def _handed_over(self, queued: list[str], fail_others: bool = False) -> list[Job]:
        """The jobs of ``queued`` handed to the runner once their uploads were complete (:meth:`submit`;
        so was any job that ran). The others are still being uploaded by a request, which submits
        them itself. At start (``fail_others``) no request is: a job whose uploads were complete (its
        ``params.json``, written last, is there: a store older than ``submitted_at``) runs, the
        others fail saying so (their uploads go)."""
        handed = []
        for job_id in queued:
            job = self.store.get(job_id)
            complete = fail_others and (self.store.directory(job_id) / "inputs" / "params.json").exists()
            if job is not None and (job.submitted_at is not None or job.started_at is not None or complete):
                handed.append(job)
            elif job is not None and fail_others and self.store.fail(job_id, INTERRUPTED):
                self.store.discard_inputs(job_id)
                log.warning(f"job {job_id} was being uploaded when the server stopped; it failed",
                            extra={"job_id": job_id})
        return handed

    def maintain(self) -> None:
        """Stop the jobs running longer than ``timeout_s``: each fails saying so (its uploads go now),
        and the pool's processes are stopped; the pool is then replaced and any other job it was
        running recovered (the module). Fail the queued jobs whose submission no request reads any
        more (a request whose clean-up could not delete its job: they would count against the queue's
        limit until a restart). First, fail the jobs whose run could not record its end where the
        store refused that at once too (:meth:`_give_up_unrecorded`)."""
        with self.lock:
            unrecorded = list(self.unrecorded)
        for job_id in unrecorded:
            self._give_up_unrecorded(job_id)
        for job in map(self.store.get, self.store.ids("queued")):
            if job is not None:
                self.store.fail_abandoned(job, SUBMISSION_LEASE_S)
        now = time.time()
        late = [job for job in map(self.store.get, self.store.ids("running"))
                if job is not None and job.ran_longer_than(self.timeout_s, now)]
        late = [job for job in late if self.store.give_up(job.id, TIMED_OUT, job.attempts)]   # not ended meanwhile
        if late:
            self._stop_workers("a timed-out job", spared=[j for j in self.store.ids("running") if j in self.futures])

    def cancel(self, job_id: str) -> None:
        """A job not yet started never starts (its run finds it cancelled in the store and ends at once);
        a running one stops now when it runs alone in the pool (its worker processes are stopped and
        replaced), else at its next stage.

        The pool's future of a job not yet started is left as it is: a cancelled future makes a pool
        whose processes are stopped fail its clean-up (the pool's thread sets an error on every future
        still waiting, and a cancelled one refuses it)."""
        future = self.futures.get(job_id)
        if future is None or future.done() or not future.running():   # done: it saw the cancel at a stage's end
            return
        job = self.store.get(job_id)
        if job is None or job.started_at is None or any(j in self.futures for j in self.store.ids("running")):
            return
        self._stop_workers("a cancelled job")

    def _stop_workers(self, reason: str, spared: list[str] | None = None) -> None:
        """Kill the pool's processes; the pool, broken, is replaced and its jobs recovered (:meth:`_replace`),
        those of ``spared`` (running beside the job stopped for) without losing an attempt.

        The runner replaces it itself once the processes are gone: the job may have ended on its own
        between the decision and the kill, and a pool whose idle worker dies fails no future, so no
        future's callback would."""
        with self.lock:
            self.stopped_for, self.spared, pool = reason, list(spared or []), self.pool
            procs = list((getattr(pool, "_processes", None) or {}).values())
            for proc in procs:
                proc.kill()

        def replace() -> None:
            for proc in procs:                         # their sentinels, not join(): the pool's thread reaps them
                multiprocessing.connection.wait([proc.sentinel], timeout=10)
            self._replace(pool)

        threading.Thread(target=replace, name="job-pool-recovery", daemon=True).start()

    def stats(self) -> dict[str, float]:
        return {"workers": float(self.workers)}

    def hand_back(self, timeout_s: float = 10.0) -> list[str]:
        """Stop every worker process (SIGTERM, then SIGKILL after ``timeout_s``) and put the jobs they
        were running back in the queue, as the server begins to stop; the run stopped so does not
        count as one of their attempts (a rolling restart never fails a job; a server killed outright
        does count, at the next start). Jobs submitted after it wait, queued, for the next start; the
        store stays this server's until :meth:`shutdown`."""
        with self.stopping:
            with self.lock:
                self.closing.set()
                running = list(self.futures)           # before the pool's end empties them
            end_pool(self.pool, grace_s=0.0, timeout_s=timeout_s)
            handed_back: list[str] = []
            if self.started:
                try:                                   # an orderly stop is not the job's fault: no attempt spent
                    started = set(self.store.ids("running")) & set(running)    # not those still waiting in the pool
                    handed_back = [j for j in self.store.recover(self.max_attempts, spared=running) if j in started]
                except StoreUnavailable:
                    log.warning("the job store cannot be written; running jobs are re-queued at the next start")
            for job_id in handed_back:
                log.info("handed a job back to the queue", extra={"job_id": job_id})
            self.started = False
            return handed_back

    def shutdown(self, timeout_s: float = 10.0) -> list[str]:
        """:meth:`hand_back` (where it has not run yet), then the store's lock given up."""
        handed_back = self.hand_back(timeout_s)
        with self.stopping:
            if self.owner is not None:
                self.owner.close()                     # the lock goes with it
            self.owner = None
        return handed_back
