"""The job-runner interface: what the API asks of a back-end (:mod:`service.jobs.backends` chooses
one), and how a worker process starts."""

from __future__ import annotations

from abc import ABC, abstractmethod

from service.core import logging as service_logging
from service.core.process_pools import ignore_interrupts, watch_parent
from service.core.threads import limit_blas_threads


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

    def live_workers(self) -> int | None:
        """How many workers serve the queue now, the ``workers`` of :meth:`stats` (None: the back-end
        cannot tell). A queued job waits for one: with none, it waits until a worker is started."""
        workers = self.stats().get("workers")
        return None if workers is None else int(workers)

    def hand_back(self) -> list[str]:
        """As the API begins to stop (before the requests under way finish): stop the jobs this
        process runs and hand them back to the queue; the jobs handed back. Workers of their own
        (the distributed back-end) run on: nothing to hand back."""
        return []

    @abstractmethod
    def shutdown(self) -> list[str]:
        """At the API's stop: the jobs handed back to the queue."""


INTERRUPTED = "the submission was interrupted before the job was queued (the server stopped); submit again"
"""A job's ``error`` when the API that stored it stopped before its uploads were complete."""


def lost_worker(max_attempts: int) -> str:
    """A job's ``error`` once the workers running it were lost ``max_attempts`` times (killed, or out
    of memory), in words with no server detail.

    Example:
        >>> lost_worker(2)
        'the worker running it was lost 2 times (SVRNET_JOB_MAX_ATTEMPTS); the job was not completed'
    """
    return (f"the worker running it was lost {max_attempts} time{'s' if max_attempts > 1 else ''} "
            "(SVRNET_JOB_MAX_ATTEMPTS); the job was not completed")


def start_worker(parent: int, log_level: str, blas_threads: int = 1) -> None:
    """A pool worker process's start: the server's JSON logging (a failed job's line carries its id
    and the kind of error), Ctrl-C left to the server (:func:`~service.core.process_pools.ignore_interrupts`),
    :func:`~service.core.process_pools.watch_parent` and the server's BLAS threads
    (:func:`~service.core.threads.limit_blas_threads`: a job runs beside the server's requests)."""
    service_logging.configure(log_level)
    ignore_interrupts()
    watch_parent(parent)
    limit_blas_threads(blas_threads)
