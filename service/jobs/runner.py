"""The job-runner interface, its two back-ends, and the choice between them.

* **embedded** (default, nothing to install): :class:`~service.jobs.store.SqliteJobStore` and a pool
  of worker processes beside the API (:class:`~service.jobs.local_runner.LocalRunner`).
* **distributed** (``SVRNET_QUEUE_URL=redis://...``): :class:`~service.jobs.redis_store.RedisJobStore`
  and an RQ queue (:class:`~service.jobs.rq_runner.RqRunner`); the API replicas only enqueue, and
  ``svrnet-worker`` processes on any machine run the jobs.

Example:
    >>> import tempfile
    >>> from service.core.settings import Settings
    >>> store, runner = open_backend(Settings(data_dir=tempfile.mkdtemp()))
    >>> type(store).__name__, type(runner).__name__
    ('SqliteJobStore', 'LocalRunner')
    >>> runner.shutdown()
    []
"""

from __future__ import annotations

import os
import threading
import time
from abc import ABC, abstractmethod

from service.core.settings import Settings
from service.jobs.store import JobStore


class JobRunner(ABC):
    """Hands jobs to workers. The API calls :meth:`submit` once a job's inputs are complete,
    :meth:`cancel` after the store marked a job cancelled, :meth:`maintain` periodically."""

    @abstractmethod
    def start(self) -> list[str]:
        """At the API's start: the jobs (re-)submitted."""

    @abstractmethod
    def submit(self, job_id: str) -> None:
        """Queue a job whose inputs are complete."""

    def cancel(self, job_id: str) -> None:  # noqa: B027 - optional: workers also check the store
        """Stop a cancelled job's worker now rather than at its next stage."""

    def maintain(self) -> None:  # noqa: B027 - optional
        """Periodic upkeep (re-deliver jobs of lost workers, fail jobs the queue gave up)."""

    def stats(self) -> dict[str, float]:
        """Numbers for the metrics (e.g. ``workers``)."""
        return {}

    @abstractmethod
    def shutdown(self) -> list[str]:
        """At the API's stop: the jobs handed back to the queue."""


def open_backend(settings: Settings) -> tuple[JobStore, JobRunner]:
    """The store and runner that ``settings`` choose: distributed when ``queue_url`` is set."""
    if settings.queue_url:
        try:
            from service.jobs.redis_store import RedisJobStore
            from service.jobs.rq_runner import RqRunner
        except ImportError as exc:
            raise RuntimeError("SVRNET_QUEUE_URL needs the queue extra: pip install 'svrnet[queue]'") from exc

        store = RedisJobStore(settings.queue_url, settings.data_dir, settings.queue_name)
        return store, RqRunner(store, settings)
    from service.jobs.local_runner import LocalRunner
    from service.jobs.store import SqliteJobStore

    sqlite = SqliteJobStore(settings.data_dir)
    return sqlite, LocalRunner(sqlite, settings.models_dir, settings.job_workers, settings.job_max_attempts)


def watch_parent(parent: int | None = None, interval_s: float = 0.5) -> None:
    """In a worker process: exit as soon as the process that started it is gone (even after its
    ``kill -9``), so no orphan keeps running a job that the queue will hand to another worker."""
    parent = os.getppid() if parent is None else parent

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(interval_s)
        os._exit(0)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()
