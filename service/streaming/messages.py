"""The contract's JSON of a stream's messages (``pose``, ``stack``, ``update``, ``summary``, ``error``).

A stream's ``pose`` and ``stack`` hold the same slice and stack objects as ``/v1/predict``'s answer
(:mod:`service.pipeline.documents` writes both); this module adds what only a stream says.

Example:
    >>> update_messages([], {})
    []
"""

from __future__ import annotations

import time

import numpy as np

from service.core.errors import ServiceError
from service.pipeline.documents import frame_report, noise_report, slice_objects, stack_report
from service.pipeline.predict import StackPrediction
from service.streaming.answers import SessionSummary, SliceAnswer, StackAnswer


def pose_object(answer: SliceAnswer, **extra: object) -> dict:
    """A stream's ``pose`` body: the fields of a ``/v1/predict`` slice for the slice as sent, its
    stack and index, how its brain was found, and ``extra`` (e.g. ``latency_ms``)."""
    p = answer.prediction
    row = slice(answer.row, answer.row + 1)
    body = slice_objects(StackPrediction(p.prepared, p.network_from_voxel[row], p.estimate.part(row), p.poses.part(row),
                                         p.reasons[row]), row)[0]
    loc = p.prepared.localisation
    body.update({"stack": answer.stack, "index": answer.index,
                 "localisation": {"method": loc.method, "confidence": round(loc.confidence, 3)}, **extra})
    return body


def stack_message(answer: StackAnswer) -> dict:
    """A stream's ``stack`` message: the stack's final poses, its consistency and localisation, the
    slices worth acquiring again and the session's coverage."""
    p = answer.prediction
    loc = p.prepared.localisation
    found = {"method": loc.method, "confidence": round(loc.confidence, 3)}
    slices = [{"stack": answer.stack, **s, "localisation": found} for s in slice_objects(p)]
    return {"type": "stack", "stack": answer.stack, "slices": slices, "consistency": stack_report(p.poses),
            "localisation": p.prepared.localisation.report(),
            "noise": noise_report(p.prepared.input_noise, p.noise_error_mm),
            "frame": frame_report(p.request_network_error_mm, p.frame_error_mm), "reacquire": _reacquire(answer.reacquire),
            "judged_alone": answer.judged_alone, "coverage": answer.coverage.report(),
            "timing_ms": {k: round(v * 1e3, 1) for k, v in answer.timings.items()}}


def update_messages(answers: list[SliceAnswer], reacquire_of: dict[str, list[tuple[int, str]]] | None = None,
                    consistency: bool = False, restated: dict[str, StackPrediction] | None = None) -> list[dict]:
    """A stream's ``update`` messages: one per stack, its slices whose pose moved (or whose accept
    flag changed), in the order given; and for each ended stack whose list of slices worth
    acquiring again a later stack's end changed (``reacquire_of``), that list now (``reacquire``),
    with the slices that moved or none. With ``consistency`` (the updates a later stack's end made
    of the stacks ended before it), each stack with moved slices carries its ``consistency`` as the
    request's stage now sees it: why its slices moved or lost their flags (a stack found
    ``mirrored`` against the later one); so does each stack in ``restated`` (those whose
    :func:`~service.streaming.answers.consistency_decisions` the later end changed), moved or not.

    Example (an earlier stack's list changed, none of its slices moved):
        >>> update_messages([], {"ax": [(3, "high_expected_error")]})
        [{'type': 'update', 'stack': 'ax', 'slices': [], 'reacquire': [{'index': 3, 'reason': 'high_expected_error'}]}]
    """
    reacquire_of, restated = reacquire_of or {}, restated or {}
    by_stack: dict[str, list[SliceAnswer]] = {}
    for a in answers:
        by_stack.setdefault(a.stack, []).append(a)
    for stack in [*reacquire_of, *restated]:
        by_stack.setdefault(stack, [])
    def told(stack: str, group: list[SliceAnswer]) -> dict:
        if stack in restated:
            return {"consistency": stack_report(restated[stack].poses)}
        return {"consistency": stack_report(group[0].prediction.poses)} if consistency and group else {}
    return [{"type": "update", "stack": stack, "slices": [pose_object(a) for a in group],
             **({"reacquire": _reacquire(reacquire_of[stack])} if stack in reacquire_of else {}), **told(stack, group)}
            for stack, group in by_stack.items()]


def end_stack_messages(answer: StackAnswer) -> list[dict]:
    """What a stack's end sends, on a stream as over MRD: the ``update`` messages of the stacks ended
    before it (each with its ``consistency`` as the request's stage now sees it), then its ``stack``."""
    return [*update_messages(answer.updates, answer.reacquire_of, consistency=True, restated=answer.restated),
            stack_message(answer)]


def _reacquire(slices: list[tuple[int, str]]) -> list[dict]:
    return [{"index": k, "reason": r} for k, r in slices]


def summary_message(summary: SessionSummary, started: float, latencies_ms: list[float]) -> dict:
    """A stream's ``summary``: the session's stacks, slices, coverage, each ended stack's slices worth
    acquiring again, the stacks that got no final poses (never ended, or their end refused: the
    slices missing below their highest one), and where its time went, with the session's length since ``started`` (``time.perf_counter``) and the median and 95th
    percentile of its pose latencies (ms)."""
    lat = np.asarray(latencies_ms, np.float64) if latencies_ms else np.zeros(1)
    session = {"session": (time.perf_counter() - started) * 1e3, "pose_latency_p50": float(np.percentile(lat, 50)),
               "pose_latency_p95": float(np.percentile(lat, 95))}
    return {"type": "summary", "stacks": summary.stacks, "slices": summary.slices,
            "coverage": summary.coverage.report(),
            "reacquire": {stack: _reacquire(slices) for stack, slices in summary.reacquire.items()},
            "unfinished": {stack: {"missing": missing} for stack, missing in summary.unfinished.items()},
            "timing_ms": {k: round(v, 1) for k, v in {**summary.compute_ms, **session}.items()}}


def error_message(e: ServiceError, **extra: object) -> dict:
    """An ``error``: the problem's fields, its RFC 7807 ``type`` as ``problem_type`` (``type`` names the message)."""
    return {"type": "error", "problem_type": e.type, "title": e.title, "status": e.status, "detail": str(e), **extra}
