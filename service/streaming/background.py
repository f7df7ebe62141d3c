"""Where the stack stages of a stream run, so that no pose waits for them.

A pose is answered on the threads that serve the stream; the stack stages (firming an open stack
up, ending a stack) take hundreds of milliseconds of numpy and Python. Two things keep them from
delaying the poses on a small CPU:

* the threads that wait for them run at :data:`BACKGROUND_NICE` below the server's priority
  (:func:`background_executor`);
* the stack-consistency fits of the firm-ups run in a separate process of that priority
  (:func:`stage_process`): in a thread they would share Python's interpreter lock with the poses,
  and each pose, handing the lock back and forth, would wait for them (docs/realtime.md, "Measured").

Example:
    >>> stage_process().submit(pow, 2, 10).result()
    1024
"""

from __future__ import annotations

import atexit
import multiprocessing
import os
import threading
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, TypeVar

from service.core.process_pools import end_pool, ignore_interrupts, watch_parent
from service.core.threads import limit_blas_threads

BACKGROUND_NICE = 10
"""How much lower the OS priority of the stack stages is than the poses'."""


def lower_priority() -> None:
    """This thread (or process) at :data:`BACKGROUND_NICE` below its priority, where the OS allows it."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), os.getpriority(os.PRIO_PROCESS, 0) + BACKGROUND_NICE)
    except (AttributeError, OSError):          # not Linux, or not allowed: equal priority
        pass


def background_executor(name: str, workers: int = 1) -> ThreadPoolExecutor:
    """Threads for the stack stages, each at a lower priority (:func:`lower_priority`)."""
    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix=name, initializer=lower_priority)


_stage_pool: ProcessPoolExecutor | None = None
_stage_pool_lock = threading.Lock()
"""Held while the stage process is started or stopped: two firm-ups that start at once share one
process, and a stop never misses one started beside it (a process nobody would end)."""


T = TypeVar("T")

STAGE_BLAS_THREADS = 1
"""The stage process's BLAS threads: its fits multiply small matrices, and it runs beside the
server's own work (:func:`~service.core.threads.limit_blas_threads`)."""


def _start_stage_process(server: int) -> None:
    """The stage process's start: a lower priority, Ctrl-C left to the server, one BLAS thread, and an
    end with the server's process ``server`` (a server killed with ``kill -9`` leaves no stage
    process behind, even one killed while this process was still starting)."""
    lower_priority()
    ignore_interrupts()
    limit_blas_threads(STAGE_BLAS_THREADS)
    watch_parent(server)


def stage_process() -> ProcessPoolExecutor:
    """The process the firm-ups' stack fits run in: one for the server's life, started on first use
    (``spawn``: a fresh interpreter, nothing of the server's threads or model sessions), at a lower
    priority and with :data:`STAGE_BLAS_THREADS`; shut down when the server exits."""
    global _stage_pool
    with _stage_pool_lock:
        if _stage_pool is None:
            _stage_pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                              initializer=_start_stage_process, initargs=(os.getpid(),))
        return _stage_pool


def stop_stage_process(timeout_s: float = 5.0) -> None:
    """End the stage process, where one was started: its pending fits cancelled, the running one given
    ``timeout_s`` to finish, then the process terminated, so that a server stopped by SIGTERM leaves
    no process behind (``shutdown(wait=False)`` alone left it, and multiprocessing's resource
    tracker with it, running after the server had gone). The next :func:`stage_process` starts a new one.

    Example (the next use starts a new process):
        >>> first = stage_process(); first.submit(int).result()
        0
        >>> stop_stage_process(); stage_process() is first
        False
    """
    global _stage_pool
    with _stage_pool_lock:
        pool, _stage_pool = _stage_pool, None
    if pool is None:
        return
    end_pool(pool, grace_s=timeout_s, timeout_s=timeout_s)


def run_in_stage_process(fn: Callable[..., T], *args: Any) -> T:
    """``fn(*args)`` in the stage process (:func:`stage_process`), waited for. A process that has died
    (the OS's memory killer, a crash) is replaced and the call run once more in the new one, so a lost
    process costs the fit it was running, not every fit of every session after it.

    Example:
        >>> run_in_stage_process(pow, 2, 10)
        1024
    """
    for attempt in range(2):
        pool = stage_process()
        try:
            return pool.submit(fn, *args).result()
        except BrokenProcessPool:
            _forget(pool)
            if attempt:
                raise
    raise AssertionError("unreachable")


def _forget(broken: ProcessPoolExecutor) -> None:
    """Drop ``broken`` as the stage process, unless another call replaced it already."""
    global _stage_pool
    with _stage_pool_lock:
        if _stage_pool is broken:
            _stage_pool = None
    end_pool(broken, grace_s=0.0, timeout_s=1.0)


atexit.register(stop_stage_process)        # once: a no-op when no process was started
