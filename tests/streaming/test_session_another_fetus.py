"""A stream's stack of another fetus: what a later stack's end decides of it reaches the client."""

from __future__ import annotations

import numpy as np

from service.streaming.messages import end_stack_messages
from service.geometry.pose import translate
from service.streaming.frames import SliceFrame
from service.streaming.options import SessionOptions
from service.streaming.session import StreamSession
from tests.support.streams import two_stacks_case


def _moved(frames: list[SliceFrame], name: str, shift_mm: tuple[float, float, float]) -> list[SliceFrame]:
    """``frames`` as another stack ``name`` whose slices lie ``shift_mm`` away in the scanner."""
    return [SliceFrame(name, f.index, f.pixels, translate(np.asarray(shift_mm)) @ f.scanner_from_voxel, f.mask)
            for f in frames]


def test_a_stack_found_apart_by_a_later_end_is_told_and_listed_for_nothing_to_acquire_again() -> None:
    """A copy of the axial stack 100 mm away (a twin's) streamed first, then the axial and coronal
    stacks of the fetus, no slice accepted (a tiny limit). At the coronal stack's end the request's fetus is theirs: the copy is
    ``apart_from_request``, its slices lose their flags (each sent again with its reason), an
    ``update`` tells its ``consistency`` and lists nothing to acquire again (no slice acquired again
    mends another fetus's stack); the axial stack, apart while it stood one against one, is told it
    is not."""
    oracle, (ax, cor), _ = two_stacks_case()
    strict = SessionOptions(mc_samples=10, bias_correction=False, max_expected_error_mm=1e-3)   # none accepted
    session = StreamSession(oracle, None, options=strict)
    answers = []
    for frames in (_moved(ax, "twin", (100.0, 0.0, 0.0)), ax, cor):
        for frame in frames:
            session.add_slice(frame)
        answers.append(session.end_stack(frames[0].stack))
    first, second, third = answers
    assert not first.prediction.poses.apart and second.reacquire_of["twin"]     # listed while it was the fetus
    messages = {m["stack"]: m for m in end_stack_messages(third) if m["type"] == "update"}
    twin = messages["twin"]
    assert twin["consistency"]["apart_from_request"] and abs(twin["consistency"]["apart_mm"] - 100.0) < 1.0
    assert twin["reacquire"] == [] and session.summary().reacquire["twin"] == []
    brain = [s for s in third.restated["twin"].reasons if s != "empty"]
    assert brain and set(brain) == {"inconsistent_with_stack"}
    assert {s["reason"] for s in twin["slices"]} == {"inconsistent_with_stack"}
    assert len(twin["slices"]) == len(brain)                           # every slice whose reason changed
    assert second.prediction.poses.apart                                # one against one: the first's fetus
    assert messages["ax"]["consistency"]["apart_from_request"] is False


def test_what_a_later_end_decides_of_an_earlier_stack_is_told_though_none_of_its_slices_moved() -> None:
    """The axial stack ends alone (pooled with none); the coronal stack's end pools the two. The
    oracle's poses are exact, so no axial slice moves or changes its flag, and the axial stack is
    still told its ``consistency`` as the request now decides it (pooled with two stacks)."""
    oracle, (ax, cor), _ = two_stacks_case()
    session = StreamSession(oracle, None, options=SessionOptions(mc_samples=10, bias_correction=False))
    for frames in (ax, cor):
        for frame in frames:
            session.add_slice(frame)
        answer = session.end_stack(frames[0].stack)
    assert not [u for u in answer.updates if u.stack == "ax"]
    (update,) = [m for m in end_stack_messages(answer) if m["type"] == "update" and m["stack"] == "ax"]
    assert update["slices"] == [] and update["consistency"]["stacks_pooled"] == 2
