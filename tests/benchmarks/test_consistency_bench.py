"""The stack-stage benchmark runs against the stage as it is (its call of ``fit_stack`` once went stale unnoticed)."""

from __future__ import annotations

from benchmarks.consistency_bench import measure


def test_the_consistency_benchmark_measures_the_stage_and_the_statistics() -> None:
    m = measure(2, 8, repeats=1)
    assert set(m) == {"stage", "shaped", "statistics"}
    assert all(v > 0 for v in m.values())
