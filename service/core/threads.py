"""Two threads for a request's long array work: the two slices of every crossing pair, two halves of the slices.

numpy does long array operations outside the GIL, so work over tens of thousands of values (the
image term's points, the MC samples of half a request's slices) runs side by side on two cores;
work over a few thousand values does not gain. One pool serves every request: a request's work
waits for the pool rather than starting threads of its own.

Example:
    >>> two_threads(lambda half: half * 10)
    [0, 10]
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")

_PREFIX = "svrnet-arrays"
_POOL = ThreadPoolExecutor(max_workers=2, thread_name_prefix=_PREFIX)


def two_threads(work: Callable[[int], T]) -> list[T]:
    """``[work(0), work(1)]``, side by side in two threads; one after the other when called from
    the pool's own threads (work that waited there for the pool would wait for itself)."""
    if threading.current_thread().name.startswith(_PREFIX):
        return [work(0), work(1)]
    return list(_POOL.map(work, (0, 1)))
