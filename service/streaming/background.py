"""Where the stack stages of a stream run, so that no pose waits for them.

A pose is answered on the threads that serve the stream; the stack stages (firming an open stack
up, ending a stack) take hundreds of milliseconds of numpy and Python. Two things keep them from
delaying the poses on a small CPU:

* the threads that wait for them run at :data:`BACKGROUND_NICE` below the server's priority
  (:func:`background_executor`);
* the stack-consistency fits of the firm-ups run in a separate process of that priority
  (:func:`stage_process`): in a thread they would share Python's interpreter lock with the poses,
  and each pose, handing the lock back and forth, waited for them (p95 of a 128 x 128 pose: 130 ms
  beside firm-ups, 27 ms median).

Example:
    >>> stage_process().submit(pow, 2, 10).result()
    1024
"""

from __future__ import annotations

import atexit
import functools
import multiprocessing
import os
import threading
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

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


@functools.cache
def stage_process() -> ProcessPoolExecutor:
    """The process the firm-ups' stack fits run in: one for the server's life, started on first use
    (``spawn``: a fresh interpreter, nothing of the server's threads or model sessions), at a lower
    priority; shut down when the server exits."""
    pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                               initializer=lower_priority)
    atexit.register(pool.shutdown, wait=False, cancel_futures=True)
    return pool
