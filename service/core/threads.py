"""Two threads for a request's long array work: two halves of the slices, every other stack.

numpy does long array operations outside the GIL, so work of many milliseconds a half (the MC
samples of half a request's slices, a pass's padded images and gradients of every other stack) runs
side by side on two cores; work of a few milliseconds (a pass of the image term over its tens of
thousands of points) does not gain: the hand-over and the GIL between numpy's calls cost what the
second core saves. One pool serves every request: a request's work waits for the pool rather than
starting threads of its own. A forked child starts its own.

Example:
    >>> two_threads(lambda half: half * 10)
    [0, 10]
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")

_PREFIX = "svrnet-arrays"


def _new_pool() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=2, thread_name_prefix=_PREFIX)


def _fresh_pool_after_fork() -> None:
    """A forked process (an RQ work horse) holds the parent's pool without its threads: work sent
    there would never run. The child starts a pool of its own."""
    global _POOL
    _POOL = _new_pool()


_POOL = _new_pool()
os.register_at_fork(after_in_child=_fresh_pool_after_fork)


def two_threads(work: Callable[[int], T]) -> list[T]:
    """``[work(0), work(1)]``, side by side in two threads; one after the other when called from
    the pool's own threads (work that waited there for the pool would wait for itself)."""
    if threading.current_thread().name.startswith(_PREFIX):
        return [work(0), work(1)]
    return list(_POOL.map(work, (0, 1)))
