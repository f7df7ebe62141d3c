"""The streaming core against a simulated truth: every pose it answers, immediate or final, places
each slice as sent where the simulation put it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from service.core.errors import InvalidParameter, SessionFull
from service.geometry import twin
from service.streaming.answers import NOT_RECEIVED
from service.streaming.frames import IncompleteStack, SliceFrame, StreamedStack
from service.streaming.options import SessionOptions, StreamLimits
from service.streaming.session import END_SHARE, StreamSession, sent_network_from_voxel
from tests.api.conftest import INFO
from tests.support.streams import SHAPE, KeyedOracle, true_sent, two_stacks_case


FAST = SessionOptions(mc_samples=10, bias_correction=False)


@pytest.fixture
def case() -> tuple[KeyedOracle, list[list[SliceFrame]], list[np.ndarray]]:
    return two_stacks_case()


def test_each_pose_places_the_slice_as_sent_where_the_simulation_put_it(case) -> None:  # noqa: ANN001
    oracle, stacks, truths = case
    session = StreamSession(oracle, None, options=FAST)
    for frames, truth in zip(stacks, truths):
        order = list(range(0, len(frames), 2)) + list(range(1, len(frames), 2))       # interleaved
        for k in order:
            a = session.add_slice(frames[k])
            got = a.prediction.poses.poses[a.row] @ a.prediction.network_from_voxel[a.row]
            assert a.index == k and np.allclose(got, true_sent(truth, k), atol=1e-6)
        final = session.end_stack(frames[0].stack)
        p = final.prediction
        got = p.poses.poses @ p.network_from_voxel
        err = np.linalg.norm(got[:, :3, 3] - np.stack([true_sent(truth, k) for k in range(len(frames))])[:, :3, 3], axis=1)
        assert err.max() < 0.5, err
        assert final.prediction.poses.fit.acquisition_order == "as-streamed"
    summary = session.summary()
    assert summary.stacks == ["ax", "cor"] and summary.slices == 2 * SHAPE[2]
    assert summary.coverage.brain_fraction > 0.5


def firmed_up(oracle: KeyedOracle, frames: list[SliceFrame]) -> tuple[StreamSession, list[SliceFrame]]:
    """A session with the first 12 slices of ``frames`` sent and their stack's model fitted (branch decided)."""
    session = StreamSession(oracle, None, options=FAST)
    for k in range(12):
        session.add_slice(frames[k])
    session.firm_up(frames[0].stack)
    assert session.fits[frames[0].stack].fit.branch_decided
    return session, frames


def test_a_slice_takes_the_branch_its_stack_decided(case) -> None:  # noqa: ANN001
    oracle, stacks, truths = case
    session, frames = firmed_up(oracle, stacks[0])
    # The network now answers the twin for the next slice: the stack's model puts it back.
    for h, pose in list(oracle.truth.items()):
        oracle.truth[h] = twin.twin(pose, INFO.symmetry_plane_x_mm)
    a = session.add_slice(frames[12])
    got = a.prediction.poses.poses[0] @ a.prediction.network_from_voxel[0]
    assert bool(a.prediction.poses.twinned[0])
    assert np.allclose(got, true_sent(truths[0], 12), atol=1e-6)


def test_an_immediate_pose_before_its_stack_decides_expects_half_its_twin_distance(case) -> None:  # noqa: ANN001
    oracle, stacks, _ = case
    session = StreamSession(oracle, None, options=FAST)
    a = session.add_slice(stacks[0][0])                      # no stack model yet: either twin may be true
    pose = a.prediction.poses.poses[a.row]
    d = float(twin.twin_distance_mm(pose, INFO.symmetry_plane_x_mm))
    floor = getattr(INFO, "expected_error_floor_mm", 0.0)
    assert d > 10.0
    assert np.isclose(a.prediction.poses.expected_error_mm[a.row], np.sqrt(0.5 ** 2 + floor ** 2 + 0.5 * d ** 2))


def test_a_network_outlier_takes_where_its_stack_puts_it_and_an_answer_near_it_is_weighed_with_it(case) -> None:  # noqa: ANN001
    oracle, stacks, truths = case
    session, frames = firmed_up(oracle, stacks[0])
    expected = session.fits["ax"].expected_error_mm
    placement_rms = float(np.sqrt(np.nanmean(expected ** 2)))
    assert placement_rms - 0.05 < session.placement_errors["ax"] < placement_rms + 0.1   # a rigid stack: no motion
    for h, pose in list(oracle.truth.items()):               # the network now answers 40 mm off
        moved = pose.copy()
        moved[:3, 3] += (40.0, 0.0, 0.0)
        oracle.truth[h] = moved
    far = session.add_slice(frames[12])
    got = far.prediction.poses.poses[0] @ far.prediction.network_from_voxel[0]
    assert np.allclose(got, true_sent(truths[0], 12), atol=1e-6)                    # the stack's placement
    for h, pose in list(oracle.truth.items()):
        pose[:3, 3] -= (40.0 - 0.02, 0.0, 0.0)
    near = session.add_slice(frames[13])                      # within its error of the placement: weighed with it
    got = near.prediction.poses.poses[0] @ near.prediction.network_from_voxel[0]
    off = np.linalg.norm(got[:3, 3] - true_sent(truths[0], 13)[:3, 3])
    assert 1e-4 < off < 0.02 - 1e-4, off                      # between the network's answer and the placement


def test_bad_slices_are_refused_and_change_nothing(case) -> None:  # noqa: ANN001
    oracle, stacks, _ = case
    session = StreamSession(oracle, None, StreamLimits(max_slices=3, max_pixels=64 * 64), FAST)
    first = stacks[0][0]
    session.add_slice(first)
    bad = [
        (SliceFrame("ax", 0, first.pixels, first.scanner_from_voxel, first.mask), "already has a slice 0"),
        (SliceFrame("ax", 1, first.pixels[:10], first.scanner_from_voxel, first.mask[:10]), "slice.shape"),
        (SliceFrame("ax", 1, np.zeros((65, 65)), first.scanner_from_voxel), "limit of 4096 pixels"),
        (SliceFrame("ax", 1, first.pixels, np.eye(3)), "slice.scanner_from_voxel"),
        (SliceFrame("ax", 1, first.pixels, stacks[1][1].scanner_from_voxel, first.mask), "axes differ"),
        (SliceFrame("ax", 1, first.pixels, first.scanner_from_voxel, None), "slice.mask"),
        (SliceFrame("ax", -1, first.pixels, first.scanner_from_voxel, first.mask), "negative"),
        (SliceFrame("ax", 1, first.pixels, first.scanner_from_voxel @ np.diag([30.0, 30.0, 1.0, 1.0])), "voxel size"),
    ]
    for frame, words in bad:
        with pytest.raises(InvalidParameter, match=words):
            session.add_slice(frame)
    assert len(session.stacks["ax"]) == 1
    lone = StreamSession(oracle, None, StreamLimits(max_slices=3, max_pixels=64 * 64), FAST)
    lone.add_slice(stacks[0][2])
    with pytest.raises(InvalidParameter, match="lacks the slices"):     # a stack of one slice and a gap
        lone.end_stack("ax")
    session.add_slice(stacks[0][1])
    session.add_slice(stacks[0][2])
    with pytest.raises(InvalidParameter, match="at most 3 slices"):
        session.add_slice(stacks[0][3])
    session.end_stack("ax")
    with pytest.raises(InvalidParameter, match="has ended with a slice 2"):
        session.add_slice(stacks[0][2])
    with pytest.raises(InvalidParameter, match="at most 3 slices"):      # one it has not had: full all the same
        session.add_slice(stacks[0][3])
    with pytest.raises(InvalidParameter, match="already ended"):
        session.end_stack("ax")


def test_a_stack_ends_without_the_slices_that_never_came_and_takes_them_when_they_do(case) -> None:  # noqa: ANN001
    """A scanner's dropped slice costs its stack that slice alone: the stack ends with it blank,
    named ``not_received`` and listed to acquire again, every slice received placed as the
    simulation put it; the slice, sent after all, reopens the stack, and its next end is whole."""
    oracle, stacks, truths = case
    frames, n = stacks[0], len(stacks[0])
    session = StreamSession(oracle, None, options=FAST)
    gone = (0, 7, 8)                                          # the first slice too: the stack's origin is inferred
    for k in range(n):
        if k not in gone:
            session.add_slice(frames[k])
    final = session.end_stack("ax")
    p = final.prediction
    assert [k for k, r in enumerate(p.reasons) if r == NOT_RECEIVED] == list(gone) and len(p.reasons) == n
    assert [(k, r) for k, r in final.reacquire if r == NOT_RECEIVED] == [(k, NOT_RECEIVED) for k in gone]
    got = p.poses.poses @ p.network_from_voxel
    err = [np.linalg.norm(got[k, :3, 3] - true_sent(truths[0], k)[:3, 3]) for k in range(n) if k not in gone]
    assert max(err) < 0.5, err
    for k in gone:                                            # a blank slice k maps as the stack's voxel (i0, i1, k)
        stack_from_sent = np.linalg.inv(p.prepared.upload.volume.affine) @ frames[k].scanner_from_voxel
        assert np.allclose(stack_from_sent, np.eye(4) + np.outer(np.eye(4)[2], np.eye(4)[3]) * k, atol=1e-6)
    # ... which is where the scanner's frame for it puts it (the stack inferred where slice 0 lies)
    unit = replace(p, network_from_voxel=np.tile(np.eye(4), (n, 1, 1)))
    assert np.allclose(sent_network_from_voxel(unit, [None if k in gone else f for k, f in enumerate(frames)]),
                       sent_network_from_voxel(unit, frames), atol=1e-6)
    assert session.summary().reacquire["ax"][:3] == [(k, NOT_RECEIVED) for k in gone]
    with pytest.raises(InvalidParameter, match=r"slice.index: stack 'ax' has ended with a slice 3; .* may still come"):
        session.add_slice(frames[3])
    held = session.held_bytes
    session.add_slice(frames[7])                              # it came after all: the stack is open again
    assert "ax" not in session.finals and session.summary().unfinished == {"ax": [0, 8]}
    assert session.held_bytes > held                          # the earlier end still held (its answers keep it)
    session.add_slice(frames[8])
    session.add_slice(frames[0])
    again = session.end_stack("ax").prediction
    assert NOT_RECEIVED not in again.reasons
    whole = StreamSession(oracle, None, options=FAST)
    for frame in frames:
        whole.add_slice(frame)
    whole.end_stack("ax")
    assert abs(session.held_bytes - whole.held_bytes) < 0.01 * whole.held_bytes, (session.held_bytes, whole.held_bytes)
    got = again.poses.poses @ again.network_from_voxel
    assert max(np.linalg.norm(got[k, :3, 3] - true_sent(truths[0], k)[:3, 3]) for k in range(n)) < 0.5


def test_slices_an_ended_stack_s_end_overtook_open_it_again(case) -> None:  # noqa: ANN001
    """A script's ``end_stack`` overtakes its last two slices: they are not refused, and not lost; they
    open the stack again (reserving memory for its next end for the slices past its first end's),
    and its next end answers the whole stack as a session that sent them in time does."""
    oracle, stacks, _ = case
    frames, n = stacks[0], len(stacks[0])
    session = StreamSession(oracle, None, options=FAST)
    for frame in frames[:-2]:
        session.add_slice(frame)
    first = session.end_stack("ax").prediction
    assert len(first.reasons) == n - 2 and NOT_RECEIVED not in first.reasons
    session.add_slice(frames[-2])
    assert "ax" not in session.finals and session.summary().unfinished == {"ax": []}
    assert session.reserved == {"ax": END_SHARE * frames[-2].pixels.size * 4}   # for the slice past its end alone
    session.add_slice(frames[-1])
    session.end_stack("ax")
    with pytest.raises(InvalidParameter, match=f"has ended with a slice {n - 1}"):    # one it has had
        session.add_slice(frames[-1])
    whole = StreamSession(oracle, None, options=FAST)
    for frame in frames:
        whole.add_slice(frame)
    expected = whole.end_stack("ax").prediction
    again = session.finals["ax"]
    assert len(again.reasons) == n and again.reasons == expected.reasons
    np.testing.assert_allclose(again.poses.poses, expected.poses.poses, atol=1e-6)


def test_a_stack_with_most_of_its_slices_missing_does_not_end(case) -> None:  # noqa: ANN001
    """A few slices sent under a stack of their own (a reacquisition) are not judged as a stack of holes."""
    oracle, stacks, _ = case
    session = StreamSession(oracle, None, options=FAST)
    for k in (4, 9):
        session.add_slice(stacks[0][k])
    with pytest.raises(IncompleteStack, match=r"lacks the slices \[0, 1, 2, 3, 5, 6, 7, 8\]"):
        session.end_stack("ax")
    for k in (0, 1, 2, 3, 5):
        session.add_slice(stacks[0][k])
    reasons = session.end_stack("ax").prediction.reasons
    assert [k for k, r in enumerate(reasons) if r == NOT_RECEIVED] == [6, 7, 8] and len(reasons) == 10


def test_a_slice_whose_index_contradicts_its_place_is_refused_on_arrival(case) -> None:  # noqa: ANN001
    oracle, stacks, _ = case
    frames = stacks[0]
    session = StreamSession(oracle, None, options=FAST)
    session.add_slice(frames[0])
    with pytest.raises(InvalidParameter, match="slice 1 sits where slice 0"):
        session.add_slice(SliceFrame("ax", 1, frames[1].pixels, frames[0].scanner_from_voxel, frames[1].mask))
    session.add_slice(frames[2])
    swapped = SliceFrame("ax", 1, frames[1].pixels, frames[3].scanner_from_voxel, frames[1].mask)
    with pytest.raises(InvalidParameter, match=r"slice.index: slice 1 of stack 'ax' lies .* where the stack's slices "
                                               r"put index 1"):
        session.add_slice(swapped)
    assert sorted(session.stacks["ax"].frames) == [0, 2]               # the stack unchanged
    for k in (5, 1, 3):                                                # their own places, in any order: taken
        session.add_slice(frames[k])
    reversed_numbering = StreamSession(oracle, None, options=FAST)     # indices may run against the normal
    n = len(frames)
    for k in (0, 3, 1):
        f = frames[n - 1 - k]
        reversed_numbering.add_slice(SliceFrame("ax", k, f.pixels, f.scanner_from_voxel, f.mask))


def test_positions_rounded_as_scanners_write_them_pass_the_arrival_check() -> None:
    """Origins rounded to 0.01 mm, the step first seen between neighbours and extrapolated 58 slices."""
    rotation = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]
    stack = StreamedStack("s")
    for k in [0, 1] + list(range(59, 1, -1)):
        a = np.eye(4)
        a[:3, :3] = rotation @ np.diag([1.1, 1.1, 3.3])
        a[:3, 3] = np.round(np.array([10.0, -20.0, 30.0]) + k * a[:3, 2], 2)
        stack.add(SliceFrame("s", k, np.zeros((4, 4), np.float32), a))
    assert stack.volume()[0].array.shape == (4, 4, 60)


def test_slice_positions_rounded_to_a_tenth_of_a_mm_are_taken_as_predict_takes_such_a_series() -> None:
    """Slices 3.304 mm apart whose positions along the normal are written rounded to 0.1 mm (steps of
    3.2 to 3.4 mm), sent in an interleaved order: every slice is taken and the stack ends (its steps
    differ from their median by under 5 %, which ``/v1/predict`` allows a series); a slice 0.3 mm off
    is refused once the step is known."""
    rotation = np.linalg.qr(np.array([[0.07, 1.0, 0.04], [1.0, -0.07, 0.03], [0.04, 0.03, -1.0]]))[0]   # 4 deg oblique
    normal = rotation[:, 2]
    stack = StreamedStack("s")

    def frame(k: int, extra_mm: float = 0.0) -> SliceFrame:
        a = np.eye(4)
        a[:3, :3] = rotation @ np.diag([1.1, 1.1, 3.3])
        a[:3, 3] = np.array([10.0, -20.0, 30.0]) + normal * (np.round(k * 3.304, 1) + extra_mm)
        return SliceFrame("s", k, np.zeros((4, 4), np.float32), a)

    for k in list(range(0, 24, 2)) + list(range(1, 23, 2)):
        stack.add(frame(k))
    with pytest.raises(InvalidParameter, match="slice.index: slice 23"):
        stack.add(frame(23, 0.3))
    stack.add(frame(23))
    assert stack.volume()[0].array.shape == (4, 4, 24)


def test_a_slice_taken_off_its_place_does_not_lock_the_stack_and_ends_dropped_to_be_sent_again(case) -> None:  # noqa: ANN001
    """Slices 0 and 1, then slice 10 0.3 mm off its place (taken: the step is known from two slices
    only), then every other slice where it belongs: each is taken (the line is the slices' robust
    one, not slice 10's). Ending the stack names slice 10 and drops it; sent again where it belongs,
    the stack ends."""
    oracle, stacks, _ = case
    frames = stacks[0]
    n = len(frames)
    session = StreamSession(oracle, None, options=FAST)
    normal = frames[0].scanner_from_voxel[:3, 2] / np.linalg.norm(frames[0].scanner_from_voxel[:3, 2])
    off = frames[10].scanner_from_voxel.copy()
    off[:3, 3] += 0.3 * normal
    for f in frames[:2] + [SliceFrame("ax", 10, frames[10].pixels, off, frames[10].mask)]:
        session.add_slice(f)
    for k in [*range(2, 10), *range(11, n)]:
        session.add_slice(frames[k])
    with pytest.raises(InvalidParameter, match=r"the slices \[10\] of stack 'ax' lie off the even spacing"):
        session.end_stack("ax")
    assert 10 not in session.stacks["ax"].frames and 10 not in session.slices["ax"]
    session.add_slice(frames[10])
    assert len(session.end_stack("ax").prediction.poses.poses) == n


def test_masks_hold_csf_sets_the_pose_mask_inset_of_mask_frames(case) -> None:  # noqa: ANN001
    oracle, stacks, _ = case
    frames = stacks[0]
    for holds, inset in ((False, 0.0), (True, 2.0)):
        session = StreamSession(oracle, None, options=SessionOptions(mc_samples=10, bias_correction=False,
                                                                     masks_hold_csf=holds))
        first = session.add_slice(frames[0])
        assert first.prediction.prepared.localisation.pose_inset_mm == inset
        for f in frames[1:]:
            session.add_slice(f)
        assert session.end_stack("ax").prediction.prepared.localisation.report()["pose_mask_inset_mm"] == inset
    with pytest.raises(InvalidParameter, match="start.masks_hold_csf: true or false"):
        SessionOptions.from_message({"masks_hold_csf": "yes"}, "start")


def test_a_session_holds_no_more_than_its_memory_limit_counting_what_it_keeps(case) -> None:  # noqa: ANN001
    """The limit counts each slice's preparation beside its pixels, and reserves its stack's end as it
    comes: a session filled to its limit ends its stacks within it."""
    oracle, stacks, _ = case
    one = stacks[0][0].pixels.size * 4
    probe = StreamSession(oracle, None, options=FAST)
    probe.add_slice(stacks[0][0])
    first = probe.held_bytes + sum(probe.reserved.values())
    assert first > (2 + END_SHARE) * one                                 # more than the pixels and the reserve
    for limit, taken in ((first + (1 + END_SHARE) * one - 1, 1), (first + (1 + END_SHARE) * one, 2)):
        session = StreamSession(oracle, None, StreamLimits(max_bytes=int(limit)), FAST)
        session.add_slice(stacks[0][0])
        if taken == 1:
            with pytest.raises(SessionFull, match="a session keeps at most"):
                session.add_slice(stacks[0][1])
        else:
            session.add_slice(stacks[0][1])
        assert len(session.stacks["ax"]) == taken
    for frame in stacks[0][1:]:
        probe.add_slice(frame)
    before = probe.held_bytes
    probe.end_stack("ax")
    assert probe.held_bytes > before and probe.reserved == {}           # the stack as prepared whole, for its reserve
    for limit in (probe.held_bytes + 6 * (1 + END_SHARE) * one, 10 * 2**20):
        full = StreamSession(oracle, None, StreamLimits(max_bytes=int(limit)), FAST)
        taken = []
        for frames in stacks:
            for frame in frames:
                try:
                    full.add_slice(frame)
                except SessionFull:
                    break
                taken.append(frame)
            if frame.stack in full.stacks and len(full.stacks[frame.stack]) > 1:
                full.end_stack(frame.stack)
                assert full.held_bytes <= limit, (full.held_bytes, limit)
        assert len(taken) > len(stacks[0])


def test_a_stack_ended_without_some_slices_ends_within_the_memory_limit(case) -> None:  # noqa: ANN001
    """A stack's end holds a blank slice for each that has not come: its reserve counts every slice
    up to its largest index, so a session whose stack lacks every other slice still ends it within
    its limit (refusing a slice first where it must), and one with room for that end takes them all."""
    oracle, stacks, _ = case
    frames = stacks[0]
    sent = [*range(0, len(frames), 2), len(frames) - 1]          # 9 of 20 missing: a stack that may end
    one = frames[0].pixels.size * 4
    probe = StreamSession(oracle, None, options=FAST)
    for k in sent:
        probe.add_slice(frames[k])
    before = probe.held_bytes
    probe.end_stack("ax")
    assert probe.held_bytes - before > (END_SHARE + 1) * len(sent) * one   # more than the slices' own share
    for limit, all_taken in ((before + END_SHARE * len(sent) * one, False), (before + END_SHARE * len(frames) * one, True)):
        session = StreamSession(oracle, None, StreamLimits(max_bytes=int(limit)), FAST)
        taken = 0
        for k in sent:
            try:
                session.add_slice(frames[k])
            except SessionFull:
                break
            taken += 1
        assert (taken == len(sent)) == all_taken, (taken, limit)
        try:
            session.end_stack("ax")
        except IncompleteStack:
            assert not all_taken
        assert session.held_bytes <= limit, (session.held_bytes, limit)


def test_a_reopened_stack_reserves_nothing_more_and_ends_again_within_its_limit(case) -> None:  # noqa: ANN001
    """A slice an ended stack lacked reopens it: its end is held already, and ending it again keeps
    as much, so the slice reserves nothing more."""
    oracle, stacks, _ = case
    frames = stacks[0]
    session = StreamSession(oracle, None, options=FAST)
    for k in range(len(frames)):
        if k != 5:
            session.add_slice(frames[k])
    session.end_stack("ax")
    session.add_slice(frames[5])
    assert session.reserved == {} and "ax" in session.reopened
    held = session.held_bytes
    session.end_stack("ax")
    assert session.reserved == {} and session.held_bytes <= held                 # the end it held, no more


def test_a_stack_holds_no_more_than_its_slice_limit_and_the_next_stack_goes_on(case) -> None:  # noqa: ANN001
    """As an upload's: the stack stage's work grows with the cube of a stack's slices. An index at
    the limit or beyond is refused at once: a stack's missing slices and its volume reach up to its
    largest index, so one slice of index 10**9 would have made them that long."""
    oracle, stacks, _ = case
    session = StreamSession(oracle, None, StreamLimits(max_stack_slices=2), FAST)
    session.add_slice(stacks[0][0])
    session.add_slice(stacks[0][1])
    with pytest.raises(InvalidParameter, match=r"slice.index: 2 is beyond the 2 slices one stack may hold"):
        session.add_slice(stacks[0][2])
    with pytest.raises(InvalidParameter, match=r"slice.index: 1000000000 is beyond"):
        session.add_slice(replace(stacks[0][2], index=10**9))
    assert len(session.stacks["ax"]) == 2 and session.summary().unfinished == {"ax": []}
    session.add_slice(stacks[1][0])                                      # another stack is taken
    assert len(session.stacks[stacks[1][0].stack]) == 1


def test_a_session_holds_no_more_than_its_stack_limit_and_its_stacks_go_on(case) -> None:  # noqa: ANN001
    """As a request's ``max_files``: each stack's end refits the ended stacks before it."""
    oracle, stacks, _ = case
    session = StreamSession(oracle, None, StreamLimits(max_stacks=1), FAST)
    session.add_slice(stacks[0][0])
    with pytest.raises(InvalidParameter, match="slice.stack: a session holds at most 1 stacks") as refused:
        session.add_slice(stacks[1][0])
    assert not isinstance(refused.value, SessionFull)                    # not the end of the session's slices
    session.add_slice(stacks[0][1])                                      # the stack it holds goes on
    assert list(session.stacks) == ["ax"] and len(session.stacks["ax"]) == 2


def test_a_stack_judged_alone_waits_for_the_next_and_no_slice_to_reacquire_is_lost(case) -> None:  # noqa: ANN001
    """Every slice over a tiny expected-error limit: the first stack's end lists none of them (the next
    stack may bring their errors down), a one-stack session's summary lists them all, and the second
    stack's end sends the first one's list as it is then, whether or not its slices moved."""
    oracle, stacks, _ = case
    strict = SessionOptions(mc_samples=10, bias_correction=False, max_expected_error_mm=1e-3)
    session = StreamSession(oracle, None, options=strict)
    for f in stacks[0]:
        session.add_slice(f)
    first = session.end_stack("ax")
    waiting = [k for k, r in enumerate(first.prediction.reasons) if r == "high_expected_error"]
    assert first.judged_alone and waiting and not any(k in waiting for k, _ in first.reacquire)
    assert [k for k, r in session.summary().reacquire["ax"] if r == "high_expected_error"] == waiting
    for f in stacks[1]:
        session.add_slice(f)
    second = session.end_stack("cor")
    assert not second.judged_alone and [k for k, _ in second.reacquire] == \
        [k for k, r in enumerate(second.prediction.reasons) if r not in (None, "empty")]
    assert "ax" in second.reacquire_of and second.reacquire_of["ax"] == session.summary().reacquire["ax"]


def test_a_stack_whose_slices_lie_closer_than_its_pixels_ends_along_its_slices(case) -> None:  # noqa: ANN001
    """Overlapping slices (1 mm apart, 1.5 mm pixels): the stream knows the slice axis, so the stack's
    acquisition order is checked along it and the stack ends with a pose for every slice (taking the
    axis of largest spacing, the order of 16 slices was checked against the rows, and refused)."""
    from dataclasses import replace

    oracle, stacks, _ = case
    frames = stacks[0]
    normal = frames[0].scanner_from_voxel[:3, 2] / np.linalg.norm(frames[0].scanner_from_voxel[:3, 2])
    session = StreamSession(oracle, None, options=FAST)
    for f in frames:
        sent = np.array(f.scanner_from_voxel, dtype=np.float64)
        sent[:3, :2] *= 1.5 / np.linalg.norm(sent[:3, :2], axis=0)               # 1.5 mm pixels
        sent[:3, 2] = normal * 3.0                                               # 3 mm thick
        sent[:3, 3] = frames[0].scanner_from_voxel[:3, 3] + f.index * 1.0 * normal   # 1 mm apart
        session.add_slice(replace(f, scanner_from_voxel=sent))
    final = session.end_stack(frames[0].stack)
    assert len(final.prediction.poses.poses) == len(frames)


def test_one_mc_pass_gives_streamed_poses_without_an_expected_error_and_accepts_none(case) -> None:  # noqa: ANN001
    """As in ``/v1/predict``: a spread never measured calibrates nothing, immediately or once the stack is fitted
    (the estimator reports one pass's variance as NaN, tests/inference/test_statistics_twin.py)."""
    oracle, stacks, _ = case
    learnt = oracle.estimate

    def one_pass(inputs: np.ndarray, mc_samples: int):  # noqa: ANN202
        est = learnt(inputs, mc_samples)
        est.variance[:] = np.nan if mc_samples < 2 else est.variance
        return est
    oracle.estimate = one_pass
    session = StreamSession(oracle, None, options=SessionOptions(mc_samples=1, bias_correction=False))
    answers = [session.add_slice(frame) for frame in stacks[0]]
    final = session.end_stack(stacks[0][0].stack).prediction
    for p in [a.prediction for a in answers] + [final]:
        assert np.isnan(p.poses.expected_error_mm).all() and all(r == "high_variance" for r in p.reasons)


def test_slices_sent_with_an_offset_are_held_as_their_magnitudes(case) -> None:  # noqa: ANN001
    """A scanner or converter that sends signed values (the magnitudes less 1000) sends the same image:
    the session holds each slice as its magnitudes, as ``/v1/predict`` reads a file so stored, and
    shows the network what the magnitudes show it."""
    oracle, stacks, _ = case
    plain, shifted = StreamSession(oracle, None, options=FAST), StreamSession(oracle, None, options=FAST)
    for frame in stacks[0][:6]:
        a = plain.add_slice(frame)
        b = shifted.add_slice(SliceFrame(frame.stack, frame.index, np.asarray(frame.pixels) - 1000.0,
                                         frame.scanner_from_voxel, frame.mask))
        np.testing.assert_allclose(b.prediction.prepared.prepared.inputs[b.row],
                                   a.prediction.prepared.prepared.inputs[a.row], atol=0.05)
    name = stacks[0][0].stack
    np.testing.assert_allclose(shifted.stacks[name].volume()[0].array, plain.stacks[name].volume()[0].array, atol=1e-3)


def test_a_streamed_stacks_air_floor_is_its_first_slices_for_every_slice(case) -> None:  # noqa: ANN001
    """Air stored with an offset (+500): the first slice, its air a floor, decides the stack's floor and
    every later slice loses the same 500, whether its own air would show a floor or not (a slice of
    tissue alone, here one without air); a file of the stack loses it as a whole."""
    oracle, stacks, _ = case
    session = StreamSession(oracle, None, options=FAST)
    frames = stacks[0][:4]
    for k, frame in enumerate(frames):
        pixels = np.asarray(frame.pixels, np.float32) + 500.0
        if k == 2:                                         # no air: no floor of its own
            pixels = pixels + np.linspace(0.0, 1.0, pixels.size, dtype=np.float32).reshape(pixels.shape)
        session.add_slice(SliceFrame(frame.stack, frame.index, pixels, frame.scanner_from_voxel, frame.mask))
    held = session.stacks[frames[0].stack].frames
    assert session.stacks[frames[0].stack].floor == 500.0
    for frame in frames:                                    # each slice's air back at 0 (+ the ramp's < 1)
        assert 0.0 <= float(held[frame.index].pixels.min()) - float(np.asarray(frame.pixels).min()) < 1e-3


def test_streamed_slices_gain_the_noise_error_of_their_stacks_input_noise_once(case) -> None:  # noqa: ANN001
    """As in ``/v1/predict``: a model calibrated with a noise error adds it once, in quadrature, to
    each immediate answer (from its stack's input noise so far: the median over the slices received),
    before and after its stack's model is fitted (whose placement error, which later answers weigh,
    holds none of it), to a firmed-up stack's poses and to the final poses; the poses are the same."""
    from dataclasses import replace

    from service.preprocess.noise import noise_error_mm, stack_noise

    oracle, stacks, _ = case
    frames = stacks[0]
    calibration = (0.0, 40.0)
    answers = {}
    for name, info in (("plain", INFO), ("noisy", replace(INFO, noise_error=calibration))):
        oracle.info = info
        session = StreamSession(oracle, None, options=FAST)
        immediate = [session.add_slice(f) for f in frames[:12]]
        session.firm_up(frames[0].stack)
        firmed = session.fits[frames[0].stack]
        immediate += [session.add_slice(f) for f in frames[12:]]
        answers[name] = (immediate, session.end_stack(frames[0].stack).prediction, firmed)
    del oracle.info                                               # the class's again
    levels = [a.prediction.prepared.input_noise for a in answers["noisy"][0]]
    assert np.isfinite(levels).all() and min(levels) > 0
    for k, (plain, noisy) in enumerate(zip(answers["plain"][0], answers["noisy"][0])):
        np.testing.assert_allclose(noisy.prediction.poses.poses, plain.prediction.poses.poses)
        np.testing.assert_allclose(noisy.prediction.poses.expected_error_mm, np.hypot(
            plain.prediction.poses.expected_error_mm, noise_error_mm(stack_noise(levels[:k + 1]), calibration)))
    np.testing.assert_allclose(answers["noisy"][2].expected_error_mm, np.hypot(
        answers["plain"][2].expected_error_mm, noise_error_mm(stack_noise(levels[:12]), calibration)))
    plain, noisy = answers["plain"][1], answers["noisy"][1]
    assert noisy.noise_error_mm == float(noise_error_mm(noisy.prepared.input_noise, calibration)) > 0
    np.testing.assert_allclose(noisy.poses.expected_error_mm, np.hypot(plain.poses.expected_error_mm, noisy.noise_error_mm))


def test_the_first_stack_message_holds_every_consistency_key_that_v1_predict_gives() -> None:
    """stream-v1: ``consistency`` as in `/v1/predict`, whose schema gives every key (null where it does not
    apply): the session's first stack, pooled with none, lacked the three pooling keys."""
    from service.streaming.messages import stack_message
    from service.api.schemas import StackConsistency
    from service.inference.registry import ModelRegistry
    from tests.support.streams import frames_of, simulated_stack

    estimator = ModelRegistry.from_directory("service/models", "default", 0).get("default")
    image, mask, affine, _ = simulated_stack(3, np.eye(3))
    session = StreamSession(estimator, None, options=SessionOptions(mc_samples=2, bias_correction=False))
    for frame in frames_of("ax", (image * 3.0 + 20.0).astype(np.float32), mask.astype(np.uint8), affine):
        session.add_slice(frame)
    consistency = stack_message(session.end_stack("ax"))["consistency"]
    assert set(consistency) == set(StackConsistency.model_fields)
    assert consistency["stacks_pooled"] is None


def test_slices_whose_brain_lost_its_signal_are_named_once_their_stack_ends_and_worth_acquiring_again() -> None:
    """Two slices darkened over most of their brain: each `pose` has no stack to judge it against
    (null); the `stack` message names them and lists them to acquire again, with reason `signal_lost`."""
    from service.streaming.messages import pose_object, stack_message
    from service.inference.registry import ModelRegistry
    from tests.support.streams import frames_of, simulated_stack

    estimator = ModelRegistry.from_directory("service/models", "default", 0).get("default")
    image, mask, affine, _ = simulated_stack(3, np.eye(3))
    image = image * 3.0 + 20.0
    dark = (image.shape[2] // 2, image.shape[2] // 2 + 2)
    for k in dark:
        inside = mask[..., k] > 0
        image[..., k][inside] = image[..., k][inside] * 0.1
    session = StreamSession(estimator, None, options=SessionOptions(mc_samples=4, bias_correction=False))
    poses = [pose_object(session.add_slice(f))["signal_lost"]
             for f in frames_of("ax", image.astype(np.float32), mask.astype(np.uint8), affine)]
    final = stack_message(session.end_stack("ax"))
    assert set(poses) == {None}
    assert [s["index"] for s in final["slices"] if s["signal_lost"]] == list(dark)
    listed = {r["index"]: r["reason"] for r in final["reacquire"]}
    assert {k: listed.get(k) for k in dark} == dict.fromkeys(dark, "signal_lost")     # the cause, whatever else


def test_slices_whose_brain_runs_out_of_the_picture_are_named_and_worth_acquiring_again_at_once() -> None:
    """The field of view ends inside the brain: each such slice's `pose` says so, and the `stack`
    message lists those not accepted with that reason even for a stack judged alone, whose slices
    held back by their expected error alone wait for the next stack (which mends no cut)."""
    from service.streaming.messages import pose_object, stack_message
    from service.inference.registry import ModelRegistry
    from tests.support.streams import frames_of, simulated_stack

    estimator = ModelRegistry.from_directory("service/models", "default", 0).get("default")
    image, mask, affine, _ = simulated_stack(3, np.eye(3))
    rows = np.flatnonzero(mask.any(axis=(1, 2)))
    end = (rows[0] + rows[-1]) // 2 + 4                            # the picture ends past the brain's middle
    options = SessionOptions(mc_samples=4, bias_correction=False, max_expected_error_mm=0.01)   # none accepted
    session = StreamSession(estimator, None, options=options)
    cut = [pose_object(session.add_slice(f))["cut_by_field_of_view"]
           for f in frames_of("ax", (image[:end] * 3.0 + 20.0).astype(np.float32), mask[:end].astype(np.uint8), affine)]
    final = stack_message(session.end_stack("ax"))
    named = [s["index"] for s in final["slices"] if s["cut_by_field_of_view"]]
    assert named and named == [k for k, c in enumerate(cut) if c]
    assert final["judged_alone"] and not any(s["accepted"] for s in final["slices"])
    assert {r["index"]: r["reason"] for r in final["reacquire"]} == dict.fromkeys(named, "cut_by_field_of_view")


def test_a_misplaced_second_slice_does_not_lock_out_the_correct_ones_after_it() -> None:
    """Slice 0 right, then an index 2 sent at slice 3's place (an off-by-one client): the two make
    no line their thickness confirms, so the correct slices after them are kept; the line they draw
    refuses only what contradicts it (slice 3, where the misplaced one sits), and the stack's end
    finds the misplaced slice off that line, to be sent again."""
    stack = StreamedStack("ax")
    place = lambda k: np.diag([1.1, 1.1, 3.3, 1.0]) + np.pad(np.array([[0.0], [0.0], [3.3 * k]]), ((0, 1), (3, 0)))  # noqa: E731
    stack.add(SliceFrame("ax", 0, np.zeros((4, 4), np.float32), place(0)))
    stack.add(SliceFrame("ax", 2, np.zeros((4, 4), np.float32), place(3)))          # misplaced
    refused = []
    for k in range(1, 12):
        if k == 2:
            continue
        try:
            stack.add(SliceFrame("ax", k, np.zeros((4, 4), np.float32), place(k)))
        except InvalidParameter as e:
            refused.append((k, str(e)))
    assert [k for k, _ in refused] == [3] and "sits where slice 2" in refused[0][1]
    assert stack.off_line() == [2]


def test_a_request_s_frame_error_holds_its_slices_back_but_lists_none_but_the_missing_to_acquire_again(case) -> None:  # noqa: ANN001
    """A model whose frame error puts every slice of the stack over the limit (onset 0, 50 mm per mm of
    the network's error): the stack's answer accepts none of them, and the slices worth acquiring
    again are still the ones that never came, each named so, since acquiring a slice again does not
    move the request's frame; the summary says the same."""
    oracle, stacks, _ = case
    oracle.info = replace(INFO, frame_error=(0.0, 50.0), max_expected_error_mm=4.0)   # the oracle errs little
    frames, n = stacks[0], len(stacks[0])
    session = StreamSession(oracle, None, options=FAST)
    gone = (0, 7, 8)
    for k in range(n):
        if k not in gone:
            session.add_slice(frames[k])
    final = session.end_stack("ax")
    p = final.prediction
    assert p.frame_error_mm > 4.0 and all(r is not None for r in p.reasons)
    assert [k for k, r in enumerate(p.own_reasons) if r == NOT_RECEIVED] == list(gone)
    assert final.reacquire == [(k, NOT_RECEIVED) for k in gone]
    assert session.summary().reacquire["ax"] == [(k, NOT_RECEIVED) for k in gone]
