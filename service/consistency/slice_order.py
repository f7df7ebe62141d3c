"""The order a stack's slices were acquired in: the candidates the motion model chooses among.

The motion model (:mod:`service.consistency.motion_model`) follows the fetus over acquisition time,
so it needs each slice's place in the acquisition. Without word from the user it chooses, by the
marginal likelihood, among the usual orders of 2D multi-slice fetal MRI: sequential, and
interleaved by 2 with either phase. The scanner knows the order, and the user may say it:

* a family (``interleaved``: either phase) or one named order;
* or the slice indices (along the stack's slice axis, 0-based, as in the response) in the order
  they were acquired, e.g. ``"0,2,4,1,3"``.

Why the user may say it: with mild motion the likelihood cannot always tell smooth motion from
network errors that change smoothly with depth, and may take a wrong order, fitting those errors as
motion; with more motion, the motion itself picks the order. Being told removes the choice (what
it changes for the shipped model is measured in docs/accuracy.md).

Example:
    >>> order = SliceOrder.parse("interleaved")
    >>> sorted(order.times(5))
    ['interleaved-even-first', 'interleaved-odd-first']
    >>> order.times(5)["interleaved-even-first"].tolist()
    [0, 3, 1, 4, 2]
    >>> SliceOrder.parse("0,2,4,1,3").times(5)["given"].tolist()
    [0, 3, 1, 4, 2]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

NAMED_ORDERS = ("sequential", "interleaved-even-first", "interleaved-odd-first")
"""The orders the stage knows by name (a sequential order acquired downwards is the same to the
motion model: a Gaussian process does not see the direction of time)."""
FAMILIES: dict[str, tuple[str, ...]] = {"auto": NAMED_ORDERS, "interleaved": NAMED_ORDERS[1:],
                                        **{name: (name,) for name in NAMED_ORDERS}}
"""What each word of the ``slice_order`` field lets the motion model choose among."""
VALUES = (f"one of {', '.join(FAMILIES)}, or the slice indices in the order they were acquired, "
          "comma-separated (e.g. 0,2,4,1,3)")
"""What a ``slice_order`` value may be, in the words every refusal of one uses."""
GIVEN = "given"
"""The name of an order given as a list of slice indices."""
FROM_FILE = "acquisition-times"
"""The name of an order read from the file (a DICOM series' per-slice acquisition times)."""
STREAMED = "as-streamed"
"""The name of an order taken from a stream: the order the scanner sent the slices in (or numbered them)."""
MAX_TEXT = 20_000
"""Longest ``slice_order`` text accepted (a list of indices of a very long stack fits easily)."""
PATTERN = r"^\s*(auto|interleaved|sequential|interleaved-even-first|interleaved-odd-first|\d{1,6}( *, *\d{1,6})*)\s*$"
"""What a ``slice_order`` value looks like (the API's schema states it; :meth:`SliceOrder.parse` decides)."""


def acquisition_orders(n: int) -> dict[str, NDArray[np.int64]]:
    """Acquisition times ``t[k]`` of slice ``k`` under each named order (:data:`NAMED_ORDERS`).

    Example:
        >>> acquisition_orders(4)["interleaved-odd-first"].tolist()
        [2, 0, 3, 1]
    """
    k = np.arange(n)
    half = (n + 1) // 2
    even_first = np.where(k % 2 == 0, k // 2, half + k // 2)
    odd_first = np.where(k % 2 == 1, k // 2, n // 2 + k // 2)
    return {"sequential": k, "interleaved-even-first": even_first, "interleaved-odd-first": odd_first}


@dataclass(frozen=True)
class SliceOrder:
    """What is known of one stack's acquisition order.

    Attributes:
        names: the named orders the motion model chooses among (:data:`FAMILIES`).
        sequence: the slice indices in the order they were acquired, when given (then ``names`` is empty).
        source: what the stage reports as the order of a ``sequence`` (:data:`GIVEN`, :data:`FROM_FILE`).
    """

    names: tuple[str, ...] = NAMED_ORDERS
    sequence: tuple[int, ...] | None = None
    source: str = GIVEN

    @property
    def known(self) -> bool:
        """Whether the request said anything (the default lets the file's times, else the stage, choose)."""
        return self != SliceOrder()

    @classmethod
    def parse(cls, text: str) -> SliceOrder:
        """The order a ``slice_order`` form value says (:class:`ValueError`, saying why, if none).

        Example:
            >>> SliceOrder.parse(" Interleaved-Odd-First ").names
            ('interleaved-odd-first',)
        """
        if len(text) > MAX_TEXT:
            raise ValueError(f"longer than {MAX_TEXT} characters")
        word = text.strip().lower()
        if word in FAMILIES:
            return cls(FAMILIES[word])
        try:
            sequence = tuple(int(part) for part in word.replace(" ", "").split(","))
        except ValueError:
            raise ValueError(VALUES) from None
        return cls((), sequence)

    def times(self, n: int) -> dict[str, NDArray[np.int64]]:
        """Candidate times ``{order: [n]}`` for a stack of ``n`` slices (:class:`ValueError` when a
        given sequence is not an ordering of its ``n`` slice indices)."""
        if self.sequence is None:
            every = acquisition_orders(n)
            return {name: every[name] for name in self.names}
        seq = np.asarray(self.sequence, dtype=np.int64)
        if len(seq) != n or not np.array_equal(np.sort(seq), np.arange(n)):
            raise ValueError(f"{len(seq)} indices given for a stack of {n} slices; give each index 0..{n - 1} once")
        t = np.empty(n, dtype=np.int64)
        t[seq] = np.arange(n)
        return {self.source: t}


def per_stack(orders: list[SliceOrder] | None, n_stacks: int) -> list[SliceOrder]:
    """One order per stack from none (the stage chooses), one (every stack) or one per stack
    (:class:`ValueError` otherwise).

    Example:
        >>> [o.names for o in per_stack([SliceOrder.parse("sequential")], 2)]
        [('sequential',), ('sequential',)]
    """
    orders = orders or [SliceOrder()]
    if len(orders) not in (1, n_stacks):
        raise ValueError(f"{len(orders)} values for {n_stacks} stacks; give none, one for every stack, or one per stack")
    return orders * n_stacks if len(orders) == 1 else list(orders)
