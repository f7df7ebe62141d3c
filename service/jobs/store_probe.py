"""The job store's health, asked with a bound on the wait.

A store that hangs (a Redis that accepts connections and answers nothing, a network path that
drops packets) costs each question its socket timeout, ten seconds. ``/readyz`` and ``/metrics``
ask the store at every probe and scrape; an orchestrator's readiness probe gives up after a second
or two, and a scrape that takes twenty seconds is a scrape lost. :class:`StoreProbe` asks on a
daemon thread and waits at most :data:`PROBE_WAIT_S`; one question is in flight at a time, so a hung
store holds one thread, not one per probe, and the next probe waits on the same question. An answer
that comes after its probe gave up is the next probe's while it is fresh (no older than the wait);
an older one is thrown away and the store asked again, so a store that failed since is seen failed.
No thread outlives its question, and none holds the interpreter's exit.

Example:
    >>> import time
    >>> StoreProbe(lambda: "up")()
    'up'
    >>> hung = StoreProbe(lambda: time.sleep(1.0) or "late", wait_s=0.05)
    >>> hung() is None, hung() is None               # the second waits on the first question
    (True, True)
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from concurrent.futures import TimeoutError as WaitedTooLong
from typing import Generic, TypeVar

Answer = TypeVar("Answer")

_now = time.monotonic

PROBE_WAIT_S = 2.0
"""How long ``/readyz`` and a ``/metrics`` scrape wait for the job store before they call it unreachable."""


def readiness(store, runner) -> tuple[bool, int | None]:  # noqa: ANN001 - a JobStore and a JobRunner
    """Whether ``store`` answers and can take jobs, and how many workers serve the queue (None where the
    store does not answer, or the back-end cannot tell): ``/readyz``'s question."""
    if not store.ping():
        return False, None
    return True, runner.live_workers()


class StoreProbe(Generic[Answer]):
    """``ask`` (a callable that asks the store) answered within ``wait_s`` (default
    :data:`PROBE_WAIT_S`), or None."""

    def __init__(self, ask: Callable[[], Answer], wait_s: float | None = None) -> None:
        self.ask, self.wait_s = ask, PROBE_WAIT_S if wait_s is None else wait_s
        self._pending: Future | None = None
        self._answered_at = 0.0
        self._delivered = True
        self._lock = threading.Lock()

    def _question(self) -> Future:
        future: Future = Future()

        def run() -> None:
            try:
                answer = self.ask()
            except BaseException as exc:  # noqa: BLE001 - handed to the waiter, who raises it
                self._answered_at = _now()
                future.set_exception(exc)
            else:
                self._answered_at = _now()
                future.set_result(answer)

        threading.Thread(target=run, name="svrnet-store-probe", daemon=True).start()
        return future

    def __call__(self) -> Answer | None:
        """The answer of the question in flight, or of a new one where none is (or the last came too
        long ago to be news); None where it does not come within :attr:`wait_s`. The question's own
        exceptions are raised here."""
        with self._lock:
            pending = self._pending
            stale = pending is not None and pending.done() and (
                self._delivered or _now() - self._answered_at > self.wait_s)
            if pending is None or stale:
                self._pending, self._delivered = self._question(), False
            pending = self._pending
        try:
            return pending.result(timeout=self.wait_s)
        except WaitedTooLong:
            return None
        finally:
            with self._lock:
                if pending is self._pending and pending.done():
                    self._delivered = True
