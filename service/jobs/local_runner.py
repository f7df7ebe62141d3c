"""The embedded back-end's runner: a pool of worker processes beside the API.

Jobs are recovered at start (interrupted ones re-queued, see
:meth:`~service.jobs.store.SqliteJobStore.recover`); on shutdown the workers are stopped and their
running jobs handed back to the queue, to be re-run after a restart (as after ``kill -9``).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import time
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path

from service.jobs.runner import JobRunner, watch_parent
from service.jobs.store import SqliteJobStore
from service.jobs.worker import run_job

log = logging.getLogger(__name__)


def _run(data_dir: str, models_dir: str, job_id: str) -> None:
    """What a pool process executes."""
    run_job(SqliteJobStore(Path(data_dir)), Path(models_dir), job_id)


class LocalRunner(JobRunner):
    """Submits queued jobs to a pool of ``workers`` processes (spawned, each exits with the server)."""

    def __init__(self, store: SqliteJobStore, models_dir: Path, workers: int = 1, max_attempts: int = 2) -> None:
        self.store, self.models_dir, self.max_attempts, self.workers = store, models_dir, max_attempts, workers
        self.pool = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                                        initializer=watch_parent, initargs=(os.getpid(),))
        self.futures: dict[str, Future] = {}

    def start(self) -> list[str]:
        queued = self.store.recover(self.max_attempts)
        for job_id in queued:
            job = self.store.get(job_id)
            if job is not None and job.attempts:
                log.info(f"re-queued job {job_id}, attempt {job.attempts + 1}",
                         extra={"job_id": job_id, "attempt": job.attempts + 1})
            self.submit(job_id)
        return queued

    def submit(self, job_id: str) -> None:
        self.store.update(job_id, submitted_at=time.time())
        self.futures[job_id] = self.pool.submit(_run, str(self.store.data_dir), str(self.models_dir), job_id)

    def cancel(self, job_id: str) -> None:
        future = self.futures.get(job_id)
        if future is not None:
            future.cancel()            # a job not yet started never starts; a running one stops at its next stage

    def stats(self) -> dict[str, float]:
        return {"workers": float(self.workers)}

    def shutdown(self, timeout_s: float = 10.0) -> list[str]:
        """Stop every worker process (SIGTERM, then SIGKILL after ``timeout_s``) and put the jobs they
        were running back in the queue."""
        processes = list((getattr(self.pool, "_processes", None) or {}).values())
        self.pool.shutdown(wait=False, cancel_futures=True)
        for proc in processes:
            if proc.is_alive():
                proc.terminate()
        for proc in processes:
            proc.join(timeout_s)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout_s)
        handed_back = [j for j in self.store.recover(self.max_attempts) if j in self.futures]
        for job_id in handed_back:
            log.info(f"handed job {job_id} back to the queue", extra={"job_id": job_id})
        return handed_back
