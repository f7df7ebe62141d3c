"""Which of the service's own poses a reconstruction job starts from (:func:`starting_inclusion`)."""

from __future__ import annotations

import numpy as np
import pytest

from service.jobs.worker import (MIN_ACCEPTED_SHARE, MIN_ACCEPTED_SLICES, posed_slices, poses_from_predict_body,
                                 start_label, starting_inclusion, starting_poses)


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


def _slices(n: int, accepted: list[bool] | None = None) -> list[dict]:
    """Slice ``k`` at z = 3.5 k (a rigid placement of 1.5 x 1.5 x 3.5 mm voxels)."""
    out = []
    for k in range(n):
        m = np.diag([1.5, 1.5, 3.5, 1.0])
        m[2, 3] = 3.5 * k
        out.append({"index": k, "accepted": True if accepted is None else accepted[k], "atlas_from_voxel": m.tolist()})
    return out


def test_uploaded_poses_are_matched_to_slices_by_their_index_not_their_place() -> None:
    spacing = [[1.5, 1.5, 3.5]]
    listed = _slices(4, [True, False, True, True])[::-1]            # as a client may list them: 3, 2, 1, 0
    body = {"stacks": [{"slices": listed}]}
    ((mats, acc),) = poses_from_predict_body(body, [4], spacing)
    np.testing.assert_allclose(mats[:, 2, 3], [0.0, 3.5, 7.0, 10.5])
    assert acc.tolist() == [True, False, True, True]
    assert [s["index"] for s in body["stacks"][0]["slices"]] == [0, 1, 2, 3]       # stored in that order
    unindexed = [{k: v for k, v in s.items() if k != "index"} for s in _slices(4)[::-1]]
    ((mats, _),) = poses_from_predict_body({"stacks": [{"slices": unindexed}]}, [4], spacing)
    np.testing.assert_allclose(mats[:, 2, 3], [10.5, 7.0, 3.5, 0.0])                 # no index: the list's order
    for indices in ([0, 1, 1, 3], [0, 1, 2, 4], [0, 1, None, 3], [0, 1, 2.0, 3], [0, 1, True, 3]):
        bad = _slices(4)
        for s, k in zip(bad, indices):
            s["index"] = k
        with pytest.raises(ValueError, match=r"stack 0: each slice's index must be one of 0..3, once each"):
            poses_from_predict_body({"stacks": [{"slices": bad}]}, [4], spacing)


def test_the_report_says_which_slices_a_job_started_from() -> None:
    """``started_from`` of a job's report, from the same rule that chose the start."""
    body = {"stacks": [{"slices": [{"atlas_from_voxel": np.eye(4).tolist(), "accepted": a, "reason": r}
                                   for a, r in ((True, None), (False, "empty"), (False, "high_expected_error"))]}]}
    assert start_label(body, starting_poses(body, min_slices=1)) == "accepted_slices"
    assert start_label(body, starting_poses(body)) == "every_slice"                    # 1 accepted: too few
    everyone = {"stacks": [{"slices": [{**x, "accepted": True} for x in body["stacks"][0]["slices"]]}]}
    assert start_label(everyone, starting_poses(everyone)) == "accepted_slices"        # all accepted: the same set


def test_poses_named_alike_are_matched_only_where_their_order_says_which_is_which() -> None:
    from service.jobs.worker import in_upload_order

    body = {"stacks": [{"index": 0, "filename": "t2.nii.gz", "slices": 1}, {"index": 1, "filename": "t2.nii.gz",
                                                                            "slices": 2}, {"index": 2, "filename": "x"}]}
    assert in_upload_order(body, ["t2.nii.gz", "t2.nii.gz", "x"]) is body                  # as /v1/predict had them
    with pytest.raises(ValueError, match="repeat"):
        in_upload_order(body, ["t2.nii.gz", "x", "t2.nii.gz"])
    with pytest.raises(ValueError, match="name every stack or none"):
        in_upload_order({"stacks": [{"filename": 7}, {"filename": "x"}]}, ["x", "y"])
    placeholders = {"stacks": [{"filename": "stacks[0]"}, {"filename": "stacks[1]"}]}
    assert in_upload_order(placeholders, ["b", "a"]) is placeholders                      # a job's own poses
