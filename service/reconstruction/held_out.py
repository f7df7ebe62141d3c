"""A reconstruction's held-out scores, whole and per stack, and the stacks the others do not predict.

The quality report (:mod:`~service.reconstruction.quality`) scores a volume by how well it predicts
what it was not given: each stack's slices from the volume of the other stacks (leave one stack
out), or with one stack its alternate slices. These functions read those scores for the choices a
job makes: which path wins (:mod:`~service.reconstruction.never_worse`), whether the volume is a
brain at all before its frame steps, how far to trust each stack's slices
(:func:`~service.reconstruction.pose_errors.refined_expected_errors`), and which stacks to leave out
because the others do not predict them (:func:`without_stacks_apart`).

Example:
    >>> from types import SimpleNamespace
    >>> r = SimpleNamespace(quality={"leave_one_stack_out": {"median_ncc": 0.8, "per_stack_median_ncc": [0.9, 0.86, 0.44]}})
    >>> held_out_score(r), stacks_apart(r, np.array([0, 1, 2]))
    (0.8, [2])
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike

from service.reconstruction.pipeline import ReconstructionResult
from service.reconstruction.quality import incoherent
from service.reconstruction.slices import SliceSet


def held_out_score(result: ReconstructionResult) -> float | None:
    """The result's leave-one-stack-out median NCC (None: not measured, e.g. a single stack)."""
    if result.quality is None:
        return None
    return result.quality["leave_one_stack_out"]["median_ncc"]


def coherence_score(result: ReconstructionResult) -> float | None:
    """The score that says whether the result is a coherent brain: its leave-one-stack-out median
    NCC, or with one stack its leave-alternate-slices-out median (None: neither measured). The frame
    steps leave a volume under :data:`~service.reconstruction.quality.MIN_HELD_OUT_NCC` alone; the
    paths are chosen by :func:`held_out_score` alone.

    Example:
        >>> from types import SimpleNamespace
        >>> coherence_score(SimpleNamespace(quality={"leave_one_stack_out": {"median_ncc": None},
        ...                                          "leave_alternate_slices_out": {"median_ncc": -0.02}}))
        -0.02
    """
    score = held_out_score(result)
    if score is None and result.quality is not None:
        return (result.quality.get("leave_alternate_slices_out") or {}).get("median_ncc")
    return score


def stack_held_out(result: ReconstructionResult, stack_index: ArrayLike) -> np.ndarray | None:
    """``[n]`` the leave-one-stack-out median NCC of each slice's stack (``stack_index``; NaN where
    not measured), or None where the result has no such score (no quality report, one stack).

    Example:
        >>> from types import SimpleNamespace
        >>> r = SimpleNamespace(quality={"leave_one_stack_out": {"per_stack_median_ncc": [0.9, None, 0.44]}})
        >>> stack_held_out(r, np.array([0, 1, 2, 2])).tolist()
        [0.9, nan, 0.44, 0.44]
    """
    per = ((result.quality or {}).get("leave_one_stack_out") or {}).get("per_stack_median_ncc")
    if not per or all(x is None for x in per):
        return None
    stacks = np.unique(stack_index)
    if len(per) != len(stacks):
        return None
    by_stack = np.array([np.nan if x is None else float(x) for x in per])
    return by_stack[np.searchsorted(stacks, np.asarray(stack_index))]


def stacks_apart(result: ReconstructionResult, stack_index: ArrayLike) -> list[int]:
    """The stacks (indices, as ``stack_index`` numbers them) that the others do not predict: their
    leave-one-stack-out median NCC under :data:`~service.reconstruction.quality.MIN_HELD_OUT_NCC`
    while at least two other stacks reach it. Such a stack is another fetus, another contrast or a
    stack far off, and its slices, pulled to where they fit the others worst, degrade the volume
    and the others' poses (docs/reconstruction.md). With two stacks neither can be told the odd one.

    Example:
        >>> from types import SimpleNamespace
        >>> r = SimpleNamespace(quality={"leave_one_stack_out": {"per_stack_median_ncc": [0.9, 0.86, 0.44]}})
        >>> stacks_apart(r, np.array([0, 0, 1, 3])), stacks_apart(r, np.array([0, 1]))
        ([3], [])
    """
    per = ((result.quality or {}).get("leave_one_stack_out") or {}).get("per_stack_median_ncc") or []
    stacks = np.unique(np.asarray(stack_index))
    if len(per) != len(stacks) or len(stacks) < 3:
        return []
    low = [int(s) for s, x in zip(stacks, per) if x is not None and incoherent(x)]
    agreeing = sum(x is not None and not incoherent(x) for x in per)
    return low if agreeing >= 2 else []


def without_stacks_apart(slice_set: SliceSet, result: ReconstructionResult,
                         again: Callable[[SliceSet, str], ReconstructionResult]) -> ReconstructionResult:
    """``result``, or the volume made ``again`` from ``slice_set`` without the slices of the stacks
    the others do not predict (:func:`stacks_apart`; ``again(kept, named)``, ``named`` the stacks'
    numbers for the progress), where its stacks predict each other. Its ``quality`` then names them
    (``stacks_left_out``); their slices are the volume's left-out ones.

    Example (stack 2 apart; the volume without it coherent):
        >>> from dataclasses import dataclass
        >>> from types import SimpleNamespace
        >>> @dataclass
        ... class Slices:                      # a SliceSet's fields that matter here
        ...     stack_index: np.ndarray
        ...     include: np.ndarray
        >>> ss = Slices(np.array([0, 1, 2, 2]), np.ones(4, bool))
        >>> first = SimpleNamespace(quality={"leave_one_stack_out": {"median_ncc": 0.8,
        ...                                                          "per_stack_median_ncc": [0.9, 0.86, 0.44]}})
        >>> made = lambda kept, named: SimpleNamespace(quality={"leave_one_stack_out": {
        ...     "median_ncc": 0.88, "per_stack_median_ncc": [0.9, 0.86, None]}, "given": kept.include.tolist()})
        >>> r = without_stacks_apart(ss, first, made)
        >>> r.quality["stacks_left_out"], r.quality["given"]
        ([2], [True, True, False, False])
    """
    apart = stacks_apart(result, slice_set.stack_index)
    if not apart:
        return result
    kept = replace(slice_set, include=np.asarray(slice_set.include, bool) & ~np.isin(slice_set.stack_index, apart))
    made = again(kept, ", ".join(map(str, apart)))
    score = held_out_score(made)
    if score is None or incoherent(score):
        return result
    made.quality = {**made.quality, "stacks_left_out": apart}
    return made
