"""A request's work stops when its client goes away: the API sets an event, the pipeline checks it
between its steps.

The event travels in a context variable, so the stages need no extra parameter: a coroutine that
sets it (:func:`cancelled_by`) and then runs a stage with ``anyio.to_thread.run_sync`` hands it to the
stage's thread (anyio runs the function in a copy of the caller's context), and a stage that fans out
to a pool hands it on with :func:`carried` . A step already under way finishes (a thread cannot be
stopped from outside); the next :func:`checkpoint` raises :class:`~service.core.errors.ClientGone`.
Outside a request (a job, a benchmark, a test calling a stage) nothing is set and checkpoints pass.

Example:
    >>> import threading
    >>> gone = threading.Event()
    >>> with cancelled_by(gone):
    ...     checkpoint()                  # the client is still there
    ...     gone.set()
    ...     try:
    ...         checkpoint()
    ...     except ClientGone as exc:
    ...         print(exc.status)
    499
    >>> checkpoint()                      # outside: nothing to stop
"""

from __future__ import annotations

import contextvars
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

from service.core.errors import ClientGone

T = TypeVar("T")

_GONE: contextvars.ContextVar[threading.Event | None] = contextvars.ContextVar("svrnet_client_gone", default=None)


@contextmanager
def cancelled_by(event: threading.Event) -> Iterator[threading.Event]:
    """Within the block (and in threads started from it with a copy of its context), :func:`checkpoint`
    raises once ``event`` is set."""
    token = _GONE.set(event)
    try:
        yield event
    finally:
        _GONE.reset(token)


def checkpoint() -> None:
    """Raise :class:`~service.core.errors.ClientGone` when the current request's client has gone away."""
    event = _GONE.get()
    if event is not None and event.is_set():
        raise ClientGone()


def carried(func: Callable[..., T]) -> Callable[..., T]:
    """``func`` carrying the current request's event, for a thread pool's worker (a pool's threads do not
    inherit the submitting thread's context): its checkpoints see the event wherever it runs.

    Example:
        >>> from concurrent.futures import ThreadPoolExecutor
        >>> with cancelled_by(threading.Event()) as gone, ThreadPoolExecutor(1) as pool:
        ...     gone.set()
        ...     pool.submit(carried(checkpoint)).exception().status
        499
    """
    event = _GONE.get()

    def run(*args: Any, **kwargs: Any) -> T:
        if event is None:
            return func(*args, **kwargs)
        with cancelled_by(event):
            return func(*args, **kwargs)

    return run
