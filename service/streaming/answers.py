"""What a stream session answers, and the rules on its answers.

A slice's pose (:class:`SliceAnswer`), a stack's final poses with the earlier slices they moved
(:class:`StackAnswer`) and the session's summary (:class:`SessionSummary`), as
:class:`~service.streaming.session.StreamSession` returns them; how far a slice's pose moved between
two answers (:func:`moved_mm`, which decides whether it is sent again) and which slices of a stack
are worth acquiring again (:func:`worth_acquiring_again`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from service.geometry import anchors
from service.inference import acceptance
from service.preprocess.field_of_view import CUT_BY_FIELD_OF_VIEW
from service.preprocess.intensity import SIGNAL_LOST
from service.pipeline.documents import stack_report
from service.pipeline.predict import StackPrediction
from service.streaming.coverage import Coverage

NOT_RECEIVED = "not_received"
"""The reason of a slice its stack ended without: it never arrived (a stream's, or an MRD series')."""


@dataclass
class SliceAnswer:
    """One slice's pose: row ``row`` of ``prediction``, whose ``network_from_voxel`` maps the slice as sent."""

    stack: str
    index: int
    prediction: StackPrediction
    row: int = 0
    compute_ms: float = 0.0


@dataclass
class StackAnswer:
    """A stack's final poses, the earlier slices they moved, what to acquire again, the coverage."""

    stack: str
    prediction: StackPrediction
    updates: list[SliceAnswer]
    reacquire: list[tuple[int, str]]
    coverage: Coverage
    timings: dict[str, float]
    judged_alone: bool = False                                   # no stack had ended before it
    reacquire_of: dict[str, list[tuple[int, str]]] = field(default_factory=dict)   # earlier stacks' lists that changed
    restated: dict[str, StackPrediction] = field(default_factory=dict)   # earlier stacks whose decisions changed


@dataclass
class SessionSummary:
    stacks: list[str]
    coverage: Coverage
    slices: int
    compute_ms: dict[str, float]
    reacquire: dict[str, list[tuple[int, str]]] = field(default_factory=dict)   # each ended stack's, final
    unfinished: dict[str, list[int]] = field(default_factory=dict)   # stacks without final poses: their missing slices


def moved_mm(a: SliceAnswer, b: SliceAnswer, reference: NDArray) -> float:
    """E.D. between the poses of two answers for one slice, in the frame ``reference`` (sent voxel ->
    a fixed network frame of the slice), so that different crops compare."""
    def pose(x: SliceAnswer) -> NDArray:
        return x.prediction.poses.poses[x.row] @ x.prediction.network_from_voxel[x.row] @ np.linalg.inv(reference)
    return float(anchors.ed(pose(a), pose(b)))


DECISIONS = ("decidable", "branch_decided", "branch_from_request", "branch_agrees_with_request", "mirrored",
             "apart_from_request", "stacks_pooled", "acquisition_order")
"""The keys of a stack's ``consistency`` that say what the request decided of it (the others measure)."""


def consistency_decisions(prediction: StackPrediction) -> dict:
    """What the request's stages decided of an ended stack: its ``consistency``'s :data:`DECISIONS`
    and whether the image stage refined it, not its measurements (numbers that move a little with
    every later stack, or turn null). A later stack's end that
    changes them (the stack found ``mirrored`` or ``apart_from_request``, its branch taken from the
    request, pooled with more stacks) is told the client with the stack's ``consistency``, whether
    or not a slice moved.

    Example:
        >>> from types import SimpleNamespace
        >>> consistency_decisions(SimpleNamespace(poses=SimpleNamespace(fit=None)))
        {'refined': False}
    """
    report = stack_report(prediction.poses) or {}
    return {k: report[k] for k in DECISIONS if k in report} | {"refined": report.get("image_consistency") is not None}


def stack_to_acquire_again(prediction: StackPrediction, judged_alone: bool) -> list[tuple[int, str]]:
    """:func:`worth_acquiring_again` of an ended stack's answer: by its slices' own accept flags (the
    request's frame error does not move with one slice acquired again), with the causes its
    preparation found (brain signal lost, brain cut by the field of view). None of a stack apart
    from the request's fetus (``StackPoses.apart``: another fetus's brain, which no slice acquired
    again mends; its ``consistency`` says so)."""
    if prediction.poses.apart:
        return []
    return worth_acquiring_again(prediction.own_reasons or prediction.reasons, judged_alone,
                                 prediction.prepared.signal_lost, prediction.prepared.cut_by_field_of_view)


def worth_acquiring_again(reasons: list[str | None], judged_alone: bool, signal_lost: Sequence[bool],
                          cut: Sequence[bool]) -> list[tuple[int, str]]:
    """``(index, reason)`` of the slices of a stack worth acquiring again: those not accepted, but
    for ``empty`` ones (no brain: nothing to gain) and, for a stack judged alone (the session's
    first), those whose only fault is their expected error: the next stack that crosses them is
    what brings it down (docs/realtime.md); and those whose brain lost its signal (``signal_lost``), accepted or not,
    with that reason before any other: it is the cause, and a slice acquired again may show the brain;
    a slice not accepted whose brain runs out of its picture (``cut``) with the reason
    :data:`~service.preprocess.field_of_view.CUT_BY_FIELD_OF_VIEW`, the likely cause, which no
    later stack mends (a field of view that holds the whole head does); but a slice that never
    arrived (:data:`NOT_RECEIVED`) is listed as such.

    Example:
        >>> no = [False] * 4
        >>> worth_acquiring_again([None, "empty", "high_expected_error", "inconsistent_with_stack"], True, no, no)
        [(3, 'inconsistent_with_stack')]
        >>> worth_acquiring_again([None, "high_expected_error"], False, no[:2], no[:2])
        [(1, 'high_expected_error')]
        >>> worth_acquiring_again([None, "high_expected_error", "inconsistent_with_stack"], False, [True] * 3, no[:3])
        [(0, 'signal_lost'), (1, 'signal_lost'), (2, 'signal_lost')]
        >>> worth_acquiring_again([None, "not_received", "empty"], True, [False, True, False], no[:3])
        [(1, 'not_received')]
        >>> worth_acquiring_again([None, "high_expected_error", "high_variance"], True, no[:3], [True, True, False])
        [(1, 'cut_by_field_of_view'), (2, 'high_variance')]
    """
    waits = {acceptance.EMPTY} | ({acceptance.HIGH_EXPECTED_ERROR} if judged_alone else set())
    return [(k, r if r == NOT_RECEIVED else SIGNAL_LOST if lost else CUT_BY_FIELD_OF_VIEW if cut_off and r else r)
            for k, (r, lost, cut_off) in enumerate(zip(reasons, map(bool, signal_lost), map(bool, cut)))
            if r != acceptance.EMPTY and (lost or (r is not None and (r not in waits or cut_off)))]
