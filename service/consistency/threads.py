"""Two threads for the image term's array work: the two slices of every pair, or two halves of the stacks.

numpy does long array operations outside the GIL, so work over a pass's points (tens of thousands)
runs side by side on two cores; work over a few thousand values does not gain. One pool serves
every request: a request's work waits for the pool rather than starting threads of its own.

Example:
    >>> two_threads(lambda half: half * 10)
    [0, 10]
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")

_POOL = ThreadPoolExecutor(max_workers=2, thread_name_prefix="image-term")


def two_threads(work: Callable[[int], T]) -> list[T]:
    """``[work(0), work(1)]``, side by side in two threads."""
    return list(_POOL.map(work, (0, 1)))
