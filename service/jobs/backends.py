"""The two job back-ends, and the choice between them.

* **embedded** (default, nothing to install): :class:`~service.jobs.sqlite_store.SqliteJobStore` and a pool
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

from service.core.settings import Settings
from service.jobs.runner import JobRunner
from service.jobs.store import JobStore


QUEUE_PACKAGES = ("redis", "rq")
"""What the ``queue`` extra installs: the distributed back-end's client and queue."""
QUEUE_EXTRA_MISSING = ("SVRNET_QUEUE_URL needs the queue extra ({name} is missing): "
                       "pip install \"svrnet[queue]\" (in a checkout: make install-queue)")
"""What a server or worker started for the distributed back-end without it says, in one line."""


def queue_extra_missing() -> str | None:
    """:data:`QUEUE_EXTRA_MISSING` naming the first of :data:`QUEUE_PACKAGES` that is not installed, or None.

    Example:
        >>> queue_extra_missing() is None or "pip install" in queue_extra_missing()
        True
    """
    import importlib.util

    for name in QUEUE_PACKAGES:
        if importlib.util.find_spec(name) is None:
            return QUEUE_EXTRA_MISSING.format(name=name)
    return None


def open_backend(settings: Settings) -> tuple[JobStore, JobRunner]:
    """The store and runner that ``settings`` choose: distributed when ``queue_url`` is set."""
    if settings.queue_url:
        try:
            from service.jobs.redis_store import RedisJobStore
            from service.jobs.rq_runner import RqRunner
        except ImportError as exc:
            raise RuntimeError(QUEUE_EXTRA_MISSING.format(name=getattr(exc, "name", None) or "redis")) from exc

        store = RedisJobStore(settings.queue_url, settings.data_dir, settings.queue_name)
        return store, RqRunner(store, settings)
    from service.jobs.local_runner import LocalRunner
    from service.jobs.sqlite_store import SqliteJobStore

    sqlite = SqliteJobStore(settings.data_dir)
    return sqlite, LocalRunner(sqlite, settings.models_dir, settings.job_workers, settings.job_max_attempts,
                               settings.log_level, settings.job_timeout_h * 3600, settings.blas_threads,
                               settings.localisers_dir)
