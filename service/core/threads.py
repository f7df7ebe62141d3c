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

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")

_POOL = ThreadPoolExecutor(max_workers=2, thread_name_prefix="arrays")


def two_threads(work: Callable[[int], T]) -> list[T]:
    """``[work(0), work(1)]``, side by side in two threads."""
    return list(_POOL.map(work, (0, 1)))
