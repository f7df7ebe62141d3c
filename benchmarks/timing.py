"""Timing for the benchmarks: the variants a ratio compares, timed alternately in one run.

A ratio of two timings holds on a loaded or drifting machine (a shared host, a laptop that throttles)
only where both met the same machine: each variant is called once to warm up, then the variants are
called one after the other in each of ``repeats`` rounds, and each keeps its best time.

Example:
    >>> times = alternated({"sum": lambda: sum(range(1000)), "sorted": lambda: sorted(range(1000))}, repeats=2)
    >>> sorted(times), all(t > 0 for t in times.values())
    (['sorted', 'sum'], True)
"""

from __future__ import annotations

import time
from collections.abc import Callable


def alternated(variants: dict[str, Callable[[], object]], repeats: int = 3, warm: bool = True) -> dict[str, float]:
    """Best seconds of each of ``variants`` over ``repeats`` rounds, every round calling each variant
    once in turn (after one warm-up call each unless ``warm`` is False)."""
    if warm:
        for fn in variants.values():
            fn()
    best = {name: float("inf") for name in variants}
    for _ in range(repeats):
        for name, fn in variants.items():
            t0 = time.perf_counter()
            fn()
            best[name] = min(best[name], time.perf_counter() - t0)
    return best
