"""Which of the service's own poses a reconstruction job starts from (:mod:`service.jobs.starting_poses`)."""

from __future__ import annotations

import numpy as np
import pytest

from service.jobs.starting_poses import (MIN_ACCEPTED_SHARE, MIN_ACCEPTED_SLICES, start_label, starting_inclusion,
                                         starting_poses)
from service.jobs.uploaded_poses import posed_slices


def _poses(*accepted: list[bool]) -> list[tuple[np.ndarray, np.ndarray]]:
    return [(np.tile(np.eye(4), (len(a), 1, 1)), np.array(a)) for a in accepted]


def _body(*reasons: list[str | None]) -> dict:
    return {"stacks": [{"slices": [{"reason": r} for r in rs]} for rs in reasons]}


def test_a_request_with_enough_accepted_slices_starts_from_those_alone() -> None:
    poses = _poses([True, True, False, True], [False, False, False])      # 3 of 7: over the default share
    assert 3 / 7 >= MIN_ACCEPTED_SHARE
    start = starting_inclusion(poses, min_slices=3)
    assert [inc.tolist() for _, inc in start] == [[True, True, False, True], [False, False, False]]
    assert all(np.array_equal(m, p) for (m, _), (p, _) in zip(start, poses))


def test_a_request_with_too_few_accepted_slices_starts_from_every_slice() -> None:
    start = starting_inclusion(_poses([True, False, False, False], [False, False, False]))      # 1 of 7
    assert [inc.tolist() for _, inc in start] == [[True] * 4, [True] * 3]


def test_empty_slices_do_not_count_towards_the_share() -> None:
    poses = _poses([True, False, False, False, False])
    body = _body([None, "empty", "empty", "empty", "high_expected_error"])
    posed = posed_slices(body)
    assert posed[0].tolist() == [True, False, False, False, True]
    assert [inc.tolist() for _, inc in starting_inclusion(poses, posed, min_slices=1)] == [[True, False, False, False, False]]
    assert [inc.tolist() for _, inc in starting_inclusion(poses)] == [[True] * 5]        # 1 of 5 counted


def test_the_flags_are_copied_not_shared() -> None:
    poses = _poses([True, True, False])
    start = starting_inclusion(poses, min_slices=2)
    assert start[0][1].tolist() == [True, True, False]
    start[0][1][0] = False
    assert poses[0][1].tolist() == [True, True, False]


def test_a_predict_body_gives_the_poses_and_the_accepted_start() -> None:
    body = {"stacks": [{"slices": [{"atlas_from_voxel": np.eye(4).tolist(), "accepted": a, "reason": r}
                                   for a, r in ((True, None), (False, "empty"), (False, "high_expected_error"))]}]}
    (mats, include), = starting_poses(body, min_slices=1)
    assert mats.shape == (3, 4, 4) and include.tolist() == [True, False, False]       # 1 of 2 posed accepted
    assert starting_poses(body, min_share=0.6, min_slices=1)[0][1].tolist() == [True, True, True]
    assert starting_poses(body)[0][1].tolist() == [True, True, True]                  # 1 slice: too few


def test_a_job_starts_from_the_slices_only_the_request_s_frame_error_held_back() -> None:
    """Slices whose expected error (6 mm) is over the 4.4 mm limit only because the request's frame
    error (5 mm) is in it are where a job starts, as the accepted ones; one over the limit without it
    (8 mm), or over the variance threshold too, is not; the report calls that start the accepted
    slices. Without a frame error the same body starts from the one accepted slice's share rule."""
    def one(accepted: bool, reason: str | None, error: float, variance: float = 100.0) -> dict:
        return {"atlas_from_voxel": np.eye(4).tolist(), "accepted": accepted, "reason": reason,
                "expected_error_mm": error, "geodesic_variance": variance}

    slices = [one(True, None, 4.0), one(False, "high_expected_error", 6.0), one(False, "high_expected_error", 6.0),
              one(False, "high_expected_error", 8.0), one(False, "high_expected_error", 6.0, variance=900.0)]
    framed = {"max_expected_error_mm": 4.4, "variance_threshold": 439.4,
              "stacks": [{"frame": {"request_network_error_mm": 28.7, "expected_error_added_mm": 5.0}, "slices": slices}]}
    start = starting_poses(framed, min_slices=1)
    assert start[0][1].tolist() == [True, True, True, False, False]
    assert start_label(framed, start) == "accepted_slices"
    bare = {**framed, "stacks": [{"slices": slices}]}
    assert starting_poses(bare, min_slices=1, min_share=0.5)[0][1].tolist() == [True] * 5   # 1 of 5: every slice


def test_a_job_starts_without_the_slices_whose_brain_lost_its_signal() -> None:
    """Their images would darken the volume where they lie: left out whether the job starts from the
    accepted slices or from every slice, unless nothing else is left; the report still says which rule
    chose the start."""
    flags = ((True, False), (True, True), (False, True), (True, False), (False, False))
    body = {"stacks": [{"slices": [{"atlas_from_voxel": np.eye(4).tolist(), "accepted": a, "reason": None if a else
                                    "high_expected_error", "signal_lost": lost} for a, lost in flags]}]}
    assert starting_poses(body, min_slices=1)[0][1].tolist() == [True, False, False, True, False]
    assert start_label(body, starting_poses(body, min_slices=1)) == "accepted_slices"
    assert starting_poses(body)[0][1].tolist() == [True, False, False, True, True]      # every slice: too few accepted
    assert start_label(body, starting_poses(body)) == "every_slice"
    assert starting_poses(body, keep_signal_lost=True)[0][1].tolist() == [True] * 5
    dark = {"stacks": [{"slices": [{**x, "signal_lost": True} for x in body["stacks"][0]["slices"]]}]}
    assert starting_poses(dark)[0][1].tolist() == [True] * 5                           # nothing else left


def test_too_few_accepted_slices_start_every_slice_whatever_their_share() -> None:
    few = [True] * (MIN_ACCEPTED_SLICES - 1) + [False] * 20                     # 29 of 49: over the share
    assert [inc.tolist() for _, inc in starting_inclusion(_poses(few))] == [[True] * 49]
    enough = [True] * MIN_ACCEPTED_SLICES + [False] * 20
    assert [inc.tolist() for _, inc in starting_inclusion(_poses(enough))] == [enough]


def test_the_report_says_which_slices_a_job_started_from() -> None:
    """``started_from`` of a job's report, from the same rule that chose the start."""
    body = {"stacks": [{"slices": [{"atlas_from_voxel": np.eye(4).tolist(), "accepted": a, "reason": r}
                                   for a, r in ((True, None), (False, "empty"), (False, "high_expected_error"))]}]}
    assert start_label(body, starting_poses(body, min_slices=1)) == "accepted_slices"
    assert start_label(body, starting_poses(body)) == "every_slice"                    # 1 accepted: too few
    everyone = {"stacks": [{"slices": [{**x, "accepted": True} for x in body["stacks"][0]["slices"]]}]}
    assert start_label(everyone, starting_poses(everyone)) == "accepted_slices"        # all accepted: the same set


@pytest.mark.parametrize("flag", ["mirrored", "apart_from_request"])
def test_a_job_never_starts_from_a_stack_the_request_found_mirrored_or_apart(flag: str) -> None:
    """A mirrored stack's slices lie on the twin of where the others put them, an apart stack's on
    another fetus's brain: left out of a start from every slice too (too few accepted), unless
    nothing else is left."""
    def stack(mirrored: bool, accepted: tuple[bool, ...]) -> dict:
        return {"consistency": {flag: mirrored}, "slices": [
            {"atlas_from_voxel": np.eye(4).tolist(), "accepted": a, "reason": None if a else "inconsistent_with_stack"}
            for a in accepted]}

    body = {"stacks": [stack(False, (True, False, False)), stack(True, (False, False, False))]}
    start = starting_poses(body)                                                         # 1 of 6: every slice
    assert [inc.tolist() for _, inc in start] == [[True, True, True], [False, False, False]]
    assert start_label(body, start) == "every_slice"
    alone = {"stacks": [stack(True, (False, False, False))]}
    assert starting_poses(alone)[0][1].tolist() == [True, True, True]                   # nothing else left


@pytest.mark.parametrize("flag", ["mirrored", "apart_from_request"])
def test_stacks_left_out_do_not_count_against_the_share_of_accepted_slices(flag: str) -> None:
    """The fetus's stack, 40 of its 60 slices accepted, and two stacks left out (none accepted): the
    job starts from those 40, as from the stack alone (before, 40 of 180 made it start from every
    slice of the fetus, its rejected ones included)."""
    def stack(out: bool, accepted: int, n: int = 60) -> dict:
        return {"consistency": {flag: out}, "slices": [
            {"atlas_from_voxel": np.eye(4).tolist(), "accepted": k < accepted,
             "reason": None if k < accepted else "inconsistent_with_stack"} for k in range(n)]}

    alone = starting_poses({"stacks": [stack(False, 40)]})
    beside = starting_poses({"stacks": [stack(False, 40), stack(True, 0), stack(True, 0)]})
    assert [int(inc.sum()) for _, inc in beside] == [40, 0, 0] == [int(alone[0][1].sum()), 0, 0]
