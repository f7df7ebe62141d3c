"""A server fault while a streamed slice is answered costs that slice's answer alone: the slice is
not kept, so it may be sent again and its stack still ends."""

from __future__ import annotations

import numpy as np
import pytest

from service.streaming import session as session_module
from service.streaming.answers import NOT_RECEIVED
from service.streaming.options import SessionOptions
from service.streaming.session import StreamSession
from tests.support.streams import true_sent, two_stacks_case

FAST = SessionOptions(mc_samples=10, bias_correction=False)


def fault(*args: object, **kwargs: object) -> None:
    raise RuntimeError("a fault of the server")


@pytest.mark.parametrize("stage", ["pose_alone", "array_bytes"])
def test_a_slice_whose_answer_fails_is_not_kept_and_may_come_again(monkeypatch: pytest.MonkeyPatch, stage: str) -> None:
    oracle, stacks, truths = two_stacks_case()
    frames = stacks[0][:6]
    session = StreamSession(oracle, None, options=FAST)
    for f in frames[:5]:
        session.add_slice(f)
    held = session.held_bytes

    with monkeypatch.context() as patch:
        patch.setattr(session_module, stage, fault)
        with pytest.raises(RuntimeError):
            session.add_slice(frames[5])
    assert 5 not in session.stacks["ax"].frames and session.held_bytes == held
    again = session.add_slice(frames[5])                     # sent again: answered
    got = again.prediction.poses.poses[again.row] @ again.prediction.network_from_voxel[again.row]
    np.testing.assert_allclose(got, true_sent(truths[0], 5), atol=1e-6)
    final = session.end_stack("ax")
    assert len(final.prediction.reasons) == 6 and NOT_RECEIVED not in final.prediction.reasons


def test_a_first_slice_whose_answer_fails_leaves_no_stack(monkeypatch: pytest.MonkeyPatch) -> None:
    oracle, stacks, _ = two_stacks_case()
    session = StreamSession(oracle, None, options=FAST)
    with monkeypatch.context() as patch:
        patch.setattr(session_module, "pose_alone", fault)
        with pytest.raises(RuntimeError):
            session.add_slice(stacks[0][0])
    assert session.stacks == {} and session.held_bytes == 0
    assert session.summary().unfinished == {}
