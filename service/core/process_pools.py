"""Ending a process pool so that no process outlives it: one way for every pool of the service.

:class:`~concurrent.futures.ProcessPoolExecutor`'s ``shutdown(wait=False)`` leaves its processes
running, and ``shutdown(wait=True)`` waits for whatever they run. :func:`end_pool` gives the running
work ``grace_s``, then terminates the processes, then kills what is left. The pool's manager thread
reaps each worker as it exits; the pool is waited for through that thread, never by joining the
workers beside it (two reapers of one child: the loser reads it as still running and would signal a
reaped pid).

Example (a pool whose one process is ended at once):
    >>> from concurrent.futures import ProcessPoolExecutor
    >>> pool = ProcessPoolExecutor(1); pool.submit(int).result()
    0
    >>> [p.is_alive() for p in end_pool(pool, grace_s=5.0)]
    [False]
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import multiprocessing.process
import os
import signal
import threading
import time
from concurrent.futures import ProcessPoolExecutor


def end_pool(pool: ProcessPoolExecutor, grace_s: float, timeout_s: float = 5.0) -> list[multiprocessing.process.BaseProcess]:
    """Shut ``pool`` down, its queued work cancelled: the running work gets ``grace_s`` to finish,
    then the processes are terminated (given ``timeout_s`` to end) and killed if still alive.
    Returns the processes it had."""
    workers = list((getattr(pool, "_processes", None) or {}).values())   # taken before the shutdown drops them
    manager = getattr(pool, "_executor_manager_thread", None)
    pool.shutdown(wait=False, cancel_futures=True)
    if manager is not None:
        manager.join(grace_s)
        if manager.is_alive():                                   # work still running past the grace
            for worker in workers:
                if worker.is_alive():
                    worker.terminate()
            manager.join(timeout_s)
    for worker in workers:
        if worker.is_alive():                                    # no manager to reap it, or it would not end
            worker.kill()
            worker.join(timeout_s)
    return workers


def watch_parent(parent: int | None = None, interval_s: float = 0.5) -> None:
    """In a pool's process: exit as soon as the process that started it is gone (even after its
    ``kill -9``), so no orphan keeps running a job that the queue will hand to another worker, or
    holds the memory of a stage nobody will ask for again. ``parent``: that process's pid, passed by
    it; the default, this process's parent when it calls this, is already the adoptive one where
    the starter died while this process was starting (a spawned interpreter takes a second)."""
    parent = os.getppid() if parent is None else parent

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(interval_s)
        os._exit(0)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def ignore_interrupts() -> None:
    """In a pool's process, at its start: ignore SIGINT. A Ctrl-C in a terminal reaches every process
    of the server's group, where an idle pool process would print a traceback of its interrupted
    wait for work; the pool's owner ends its processes itself (:func:`end_pool`)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def release_memory() -> None:
    """In a long-lived pool process, after a large piece of work: collect what cycles hold and hand
    the C heap's free pages back to the system (glibc's ``malloc_trim``; a C library without it,
    musl or macOS's, keeps them), so that an idle process does not keep its last job's peak.

    Example:
        >>> release_memory()
    """
    gc.collect()
    trim_heap()


def trim_heap() -> None:
    """Hand the C heap's free pages back to the system (glibc's ``malloc_trim``; elsewhere nothing).
    The many threads of a request's stages each leave an arena of freed pages behind: the server
    trims them once no request is processing (:func:`~service.api.deps.processing`). ctypes lets
    other threads run meanwhile.

    Example:
        >>> trim_heap()
    """
    try:
        ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
