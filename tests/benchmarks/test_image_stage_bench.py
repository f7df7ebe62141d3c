"""The image-stage benchmark times the refinement as it runs, and leaves the service's setting as it was."""

from __future__ import annotations

import numpy as np

import service.consistency.image_refinement as image_refinement
from benchmarks.image_stage_bench import timed
from tests.consistency.conftest import disturbed, prepared_acquisition


def test_the_image_stage_benchmark_times_both_ways_and_restores_the_setting() -> None:
    images, truth = prepared_acquisition()
    start, expected = disturbed(truth, 1.0, 1.0, seed=1), [np.full(len(t), 3.0) for t in truth]
    kept = image_refinement.MATCHED_FROM_PASS
    times = timed(images, start, expected, repeats=1)
    assert set(times) == {"plain", "matched"} and all(t > 0 for t in times.values())
    assert image_refinement.MATCHED_FROM_PASS == kept
