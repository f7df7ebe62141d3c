"""The ONNX estimator: a slice with nothing in it is not run, and the others do not notice."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from service.inference.estimator import OnnxPoseEstimator, PoseEstimate, statistics
from service.inference.model_file import load_model
from tests.api.conftest import tiny_model_path  # noqa: F401 - fixture


@pytest.mark.parametrize("views", [1, 8])
def test_an_all_zero_input_is_not_run_and_the_others_get_what_they_get_beside_it(tiny_model_path, views: int) -> None:  # noqa: ANN001, F811
    est = OnnxPoseEstimator(load_model(tiny_model_path))
    est.info = dataclasses.replace(est.info, tta_views=views)
    size = est.info.input_size
    x = np.random.default_rng(1).uniform(0, 255, (5, size, size)).astype(np.float32)
    x[[1, 4]] = 0.0
    run_rows = []
    model_run = est.model.run
    est.model.run = lambda rows, *a: (run_rows.append(len(rows)), model_run(rows, *a))[1]  # count the rows run
    out = est.estimate(x, 16)
    assert sum(run_rows) == 3 * views                        # the two empty slices never reach the network
    assert out.estimated.tolist() == [True, False, True, True, False]
    assert np.isnan(out.variance[[1, 4]]).all() and np.isnan(out.spread_mm[[1, 4]]).all()
    assert not out.degenerate[[1, 4]].any()
    # every slice run, the empty ones included (as the estimator did before it skipped them): the same
    # statistics for the slices with content, because the draws belong to the views, not to the rows
    full = statistics(est.sample_labels(x, 16), est.info.label_type, est.info.symmetry_plane_x_mm)
    for name in ("mean", "variance", "degenerate", "twin_mass", "spread_mm"):
        np.testing.assert_allclose(getattr(out, name)[out.estimated], getattr(full, name)[out.estimated], rtol=1e-6, atol=1e-6)


def test_a_request_of_empty_slices_only_runs_nothing(tiny_model_path) -> None:  # noqa: ANN001, F811
    est = OnnxPoseEstimator(load_model(tiny_model_path))
    size = est.info.input_size
    out = est.estimate(np.zeros((3, size, size), np.float32), 10)
    assert isinstance(out, PoseEstimate) and len(out.mean) == 3 and not out.estimated.any()
    np.testing.assert_array_equal(out.mean, np.broadcast_to(np.eye(4), (3, 4, 4)))


def test_calls_run_two_at_a_time_give_each_row_its_own_labels(tiny_model_path) -> None:  # noqa: ANN001, F811
    """Rows in three groups (three draws), in calls of 4 rows run two at a time, get the labels each
    group gets from one call of its own with its draws: where a call runs is a matter of speed."""
    from service.core.threads import available_cores

    side, alone = load_model(tiny_model_path), load_model(tiny_model_path, threads=1)
    assert side.side_by_side == (available_cores() >= 2) and not alone.side_by_side
    size = side.info.input_size
    x = np.random.default_rng(2).uniform(0, 255, (30, size, size)).astype(np.float32)
    est = OnnxPoseEstimator(side, batch_slices=4)
    out = est.run(x, 8, group=10)
    passes = np.ones(8, np.float32)
    expected = np.concatenate([alone.run(x[g * 10:(g + 1) * 10], passes, g) for g in range(3)])
    assert out.shape == expected.shape and np.abs(out - expected).max() < 1e-4


def test_a_large_request_is_estimated_in_chunks_that_bound_its_samples_and_change_no_statistic(
        tiny_model_path, monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: ANN001, F811
    """Slices x samples over :data:`MAX_SAMPLES_AT_ONCE` go through the network and the reduction in
    chunks of at most that many samples (memory bounded by the chunk, not the request), and every
    slice's statistics are those of one call with all of them."""
    from service.inference import estimator

    est = OnnxPoseEstimator(load_model(tiny_model_path))
    size = est.info.input_size
    x = np.random.default_rng(3).uniform(0, 255, (23, size, size)).astype(np.float32)
    x[5] = 0.0
    whole = est.estimate(x, 12)
    monkeypatch.setattr(estimator, "MAX_SAMPLES_AT_ONCE", 5 * 12)
    held = []
    sample_labels = est.sample_labels
    est.sample_labels = lambda rows, n: (held.append(len(rows) * n), sample_labels(rows, n))[1]
    chunked = est.estimate(x, 12)
    assert held == [60, 60, 60, 60, 24] and max(held) <= estimator.MAX_SAMPLES_AT_ONCE
    for name in ("mean", "variance", "degenerate", "twin_mass", "spread_mm"):
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name))
    assert set(chunked.timings) == {"inference", "statistics"}


@pytest.mark.parametrize(("collapsed", "degenerate"), [(0, False), (4, False), (5, False), (6, True), (10, True)])
def test_a_slice_is_degenerate_where_most_of_its_samples_collapse_their_anchors(collapsed: int,
                                                                                degenerate: bool) -> None:
    """Of a slice's ten MC samples, ``collapsed`` put its third anchor point on top of its first (no
    plane through them): the slice is ``degenerate`` (it neither votes in its stack nor is accepted)
    where they are more than half."""
    from service.geometry import encodings
    from service.inference.estimator import slice_statistics

    good = encodings.encode("anchor", np.eye(4)[None])[0]
    bad = good.reshape(3, 3).copy()
    bad[2] = bad[0] + 1.0
    lab = np.stack([bad.ravel() if k < collapsed else good for k in range(10)])[None]
    assert slice_statistics(lab, "anchor").degenerate.tolist() == [degenerate]
