"""What a stream session keeps in memory, for its limit (:attr:`~service.streaming.options.StreamLimits.max_bytes`).

A session keeps each slice's pixels and, beside them, its preparation alone (its volume, mask,
network inputs and statistics) and each ended stack as prepared whole: about three times the
pixels. :func:`array_bytes` counts the numpy arrays an object holds, each memory block once.
"""

from __future__ import annotations

import numpy as np


def _base(array: np.ndarray) -> np.ndarray:
    while isinstance(array.base, np.ndarray):
        array = array.base
    return array


def array_bytes(*roots: object, besides: tuple[np.ndarray, ...] = ()) -> int:
    """The bytes of the numpy arrays ``roots`` hold through their attributes, lists, tuples and dicts,
    each array's memory counted once and that of ``besides`` not at all: what a session keeps of a
    slice or a stack beyond its pixels, for its memory limit.

    Example (a view costs nothing more than its base):
        >>> a = np.zeros((10, 10), np.float32)
        >>> array_bytes({"a": a, "view": a[:5]}, [np.ones(4)]), array_bytes([a], besides=(a,))
        (432, 0)
    """
    counted = {id(_base(b)) for b in besides}
    seen, total, todo = set(), 0, list(roots)
    while todo:
        item = todo.pop()
        if id(item) in seen:
            continue
        seen.add(id(item))
        if isinstance(item, np.ndarray):
            base = _base(item)
            if id(base) not in counted:
                counted.add(id(base))
                total += base.nbytes
        elif isinstance(item, dict):
            todo.extend(item.values())
        elif isinstance(item, (list, tuple)):
            todo.extend(item)
        elif hasattr(item, "__dict__") and not isinstance(item, type):
            todo.extend(vars(item).values())
    return total


__all__ = ["array_bytes"]
