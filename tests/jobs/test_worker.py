"""Which of the service's own poses a reconstruction job starts from (:func:`starting_inclusion`)."""

from __future__ import annotations

import numpy as np

from service.jobs.worker import (MIN_ACCEPTED_SHARE, MIN_ACCEPTED_SLICES, posed_slices, start_label,
                                 starting_inclusion, starting_poses)


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


def test_the_queues_time_limit_says_so_even_where_a_reader_turned_it_into_its_own_error() -> None:
    from service.core.errors import UnsupportedFile
    from service.jobs.worker import TIMED_OUT, failure_reason

    class JobTimeoutException(Exception):              # RQ's, raised by its alarm wherever the job is
        pass

    try:
        try:
            raise JobTimeoutException("Task exceeded maximum timeout value (1 seconds)")
        except Exception as exc:
            raise UnsupportedFile("stack0.nii.gz: could not be read (corrupt, truncated or inconsistent file)") from exc
    except UnsupportedFile as err:
        assert failure_reason(err) == TIMED_OUT
    assert failure_reason(UnsupportedFile("stack0.nii.gz: could not be read")) == "stack0.nii.gz: could not be read"
