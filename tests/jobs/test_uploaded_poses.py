"""Poses a client sends with a job, read and checked against its uploads (:mod:`service.jobs.uploaded_poses`)."""

from __future__ import annotations

import numpy as np
import pytest

from service.jobs.uploaded_poses import accepted_without_frame, expected_errors, in_upload_order, poses_from_predict_body


def _slices(n: int, accepted: list[bool] | None = None) -> list[dict]:
    """Slice ``k`` at z = 3.5 k (a rigid placement of 1.5 x 1.5 x 3.5 mm voxels)."""
    out = []
    for k in range(n):
        m = np.diag([1.5, 1.5, 3.5, 1.0])
        m[2, 3] = 3.5 * k
        out.append({"index": k, "accepted": True if accepted is None else accepted[k], "atlas_from_voxel": m.tolist()})
    return out


def test_uploaded_poses_are_matched_to_slices_by_their_index_not_their_place() -> None:
    affines = [np.diag([1.5, 1.5, 3.5, 1.0])]
    listed = _slices(4, [True, False, True, True])[::-1]            # as a client may list them: 3, 2, 1, 0
    body = {"stacks": [{"slices": listed}]}
    ((mats, acc),) = poses_from_predict_body(body, [4], affines)
    np.testing.assert_allclose(mats[:, 2, 3], [0.0, 3.5, 7.0, 10.5])
    assert acc.tolist() == [True, False, True, True]
    assert [s["index"] for s in body["stacks"][0]["slices"]] == [0, 1, 2, 3]       # stored in that order
    unindexed = [{k: v for k, v in s.items() if k != "index"} for s in _slices(4)[::-1]]
    ((mats, _),) = poses_from_predict_body({"stacks": [{"slices": unindexed}]}, [4], affines)
    np.testing.assert_allclose(mats[:, 2, 3], [10.5, 7.0, 3.5, 0.0])                 # no index: the list's order
    for indices in ([0, 1, 1, 3], [0, 1, 2, 4], [0, 1, None, 3], [0, 1, 2.0, 3], [0, 1, True, 3]):
        bad = _slices(4)
        for s, k in zip(bad, indices):
            s["index"] = k
        with pytest.raises(ValueError, match=r"stack 0: each slice's index must be one of 0..3, once each"):
            poses_from_predict_body({"stacks": [{"slices": bad}]}, [4], affines)


def test_poses_named_alike_are_matched_only_where_their_order_says_which_is_which() -> None:
    body = {"stacks": [{"index": 0, "filename": "t2.nii.gz", "slices": 1}, {"index": 1, "filename": "t2.nii.gz",
                                                                            "slices": 2}, {"index": 2, "filename": "x"}]}
    assert in_upload_order(body, ["t2.nii.gz", "t2.nii.gz", "x"]) is body                  # as /v1/predict had them
    with pytest.raises(ValueError, match="repeat"):
        in_upload_order(body, ["t2.nii.gz", "x", "t2.nii.gz"])
    with pytest.raises(ValueError, match="name every stack or none"):
        in_upload_order({"stacks": [{"filename": 7}, {"filename": "x"}]}, ["x", "y"])
    placeholders = {"stacks": [{"filename": "stacks[0]"}, {"filename": "stacks[1]"}]}
    assert in_upload_order(placeholders, ["b", "a"]) is placeholders                      # a job's own poses


def test_a_job_reads_each_slice_without_its_request_s_frame_error() -> None:
    """The frame error added to every slice of a request (5 mm here) is the request's placement, which
    the job re-estimates: each slice's expected error is read without it, and a slice rejected for
    an expected error that only it put over the limit is one the job starts from. A slice over the
    limit without it, or rejected for another reason, is not; a body without a frame object (an
    earlier version's, a client's) is read as it is."""
    def one(e: float, reason: str | None) -> dict:
        return {"expected_error_mm": e, "reason": reason, "accepted": reason is None}

    stack = {"frame": {"request_network_error_mm": 23.0, "expected_error_added_mm": 5.0},
             "slices": [one(3.0, None), one(np.hypot(4.0, 5.0), "high_expected_error"),
                        one(np.hypot(5.0, 5.0), "high_expected_error"), one(np.hypot(2.0, 5.0), "high_variance")]}
    body = {"max_expected_error_mm": 4.4, "stacks": [stack, {"slices": [one(4.0, None), one(5.0, "high_expected_error")]}]}
    np.testing.assert_allclose(expected_errors(body), [0.0, 4.0, 5.0, 2.0, 4.0, 5.0], atol=1e-9)
    assert [a.tolist() for a in accepted_without_frame(body)] == [[True, True, False, False], [True, False]]
