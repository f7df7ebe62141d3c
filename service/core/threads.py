"""Threads for array work: two for a request's long array work, and the limit on numpy's and scipy's BLAS.

**Two threads** for a request's long array work: two halves of the slices, every other stack, and
the network calls of a stack (:func:`side_by_side`).

numpy does long array operations outside the GIL, so work of many milliseconds a half (the MC
samples of half a request's slices, a pass's padded images and gradients of every other stack) runs
side by side on two cores; work of a few milliseconds (a pass of the image term over its tens of
thousands of points) does not gain: the hand-over and the GIL between numpy's calls cost what the
second core saves. One pool serves every request: a request's work waits for the pool rather than
starting threads of its own. A forked child starts its own.

**BLAS** (:func:`limit_blas_threads`): the consistency stages multiply many small matrices, which
one thread does faster, and OpenBLAS threads that wait for work spin: on a machine whose cores are
busy (a server's inference, a job beside it) a BLAS thread per core makes the stack fits many times
slower ([benchmarks](docs/benchmarks.md)). Every process of the service that runs them limits its BLAS: the server, ``svrnet-mrd``,
the streams' stage process, the job workers.

Example:
    >>> two_threads(lambda half: half * 10)
    [0, 10]
    >>> side_by_side(lambda x: x * x, [1, 2, 3])
    [1, 4, 9]
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

T = TypeVar("T")
X = TypeVar("X")

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
    return side_by_side(work, (0, 1))


def side_by_side(work: Callable[[X], T], items: Sequence[X]) -> list[T]:
    """``[work(x) for x in items]``, two at a time in the pool's two threads, in order; one after
    the other when called from the pool's own threads (work that waited there for the pool would
    wait for itself) or for a single item.

    onnxruntime releases the GIL while it runs, and a small network's convolutions (a few to tens of
    channels) gain little from a second intra-op thread: two calls side by side, each on half the
    cores, run a stack's batches in about half the time one call on all the cores takes."""
    if len(items) < 2 or threading.current_thread().name.startswith(_PREFIX):
        return [work(x) for x in items]
    return list(_POOL.map(work, items))


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the system tells it)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _load_blas() -> None:
    """Load numpy's BLAS and scipy's own (a thread limit reaches only the libraries a process has loaded)."""
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401


def limit_blas_threads(threads: int) -> Any:
    """Limit numpy's and scipy's BLAS libraries (each loaded first: a limit reaches only the libraries
    a process has loaded) to ``threads`` threads for the rest of the process; 0 leaves them as they
    are. Returns the limiter (its ``restore_original_limits()`` undoes it), or None.

    Example:
        >>> limiter = limit_blas_threads(1); set(blas_threads())
        {1}
        >>> limiter.restore_original_limits()
    """
    if threads <= 0:
        return None
    _load_blas()
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=threads, user_api="blas")


def blas_threads() -> list[int]:
    """The thread count of each BLAS library this process has loaded (numpy's and scipy's, loaded
    first): what :func:`limit_blas_threads` set."""
    _load_blas()
    from threadpoolctl import threadpool_info

    return [int(lib["num_threads"]) for lib in threadpool_info() if lib.get("user_api") == "blas"]
