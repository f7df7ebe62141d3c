"""The job store's health, asked with a bound on the wait.

A store that hangs (a Redis that accepts connections and answers nothing, a network path that
drops packets) costs each question its socket timeout, ten seconds. ``/readyz`` and ``/metrics``
ask the store at every probe and scrape; an orchestrator's readiness probe gives up after a second
or two, and a scrape that takes twenty seconds is a scrape lost. :class:`StoreProbe` asks on a
thread of its own and waits at most :data:`PROBE_WAIT_S`; one question is in flight at a time, so a
hung store holds one thread, not one per probe, and the next probe waits on the same question. An
answer that came after its probe gave up is the next probe's (a slow store is seen as it is, every
other probe).

Example:
    >>> import time
    >>> quick = StoreProbe(lambda: "up")
    >>> quick()
    'up'
    >>> hung = StoreProbe(lambda: time.sleep(0.5) or "late", wait_s=0.05)
    >>> hung() is None, hung() is None               # the second waits on the first question
    (True, True)
    >>> time.sleep(0.6); hung()                      # answered meanwhile: that answer is the next probe's
    'late'
    >>> hung() is None                               # then a question is asked afresh
    True
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as WaitedTooLong
from typing import Generic, TypeVar

Answer = TypeVar("Answer")

PROBE_WAIT_S = 2.0
"""How long ``/readyz`` and a ``/metrics`` scrape wait for the job store before they call it unreachable."""


def readiness(store, runner) -> tuple[bool, int | None]:  # noqa: ANN001 - a JobStore and a JobRunner
    """Whether ``store`` answers and can take jobs, and how many workers serve the queue (None where the
    store does not answer, or the back-end cannot tell): ``/readyz``'s question."""
    if not store.ping():
        return False, None
    return True, runner.live_workers()


class StoreProbe(Generic[Answer]):
    """``ask`` (a callable that asks the store) answered within ``wait_s``, or None."""

    def __init__(self, ask: Callable[[], Answer], wait_s: float | None = None) -> None:
        self.ask, self.wait_s = ask, PROBE_WAIT_S if wait_s is None else wait_s
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="svrnet-store-probe")
        self._pending: Future | None = None
        self._delivered = True
        self._lock = threading.Lock()

    def __call__(self) -> Answer | None:
        """The answer of the question in flight, or of a new one where none is; None where it does not
        come within :attr:`wait_s`. The question's own exceptions are raised here."""
        with self._lock:
            if self._pending is None or (self._pending.done() and self._delivered):
                self._pending, self._delivered = self._pool.submit(self.ask), False
            pending = self._pending
        try:
            answer = pending.result(timeout=self.wait_s)
        except WaitedTooLong:
            return None
        finally:
            if pending.done():
                with self._lock:
                    self._delivered = self._delivered or pending is self._pending
        return answer
