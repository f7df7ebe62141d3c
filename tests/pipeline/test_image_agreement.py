"""The image stage lowers its slices' expected errors only where its refinement brought them into
agreement: where the slices still disagree after it (a run of slices whose brain lost its signal
bends their stack-mates), the stack stage's expected errors stand."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from service.consistency.image_refinement import Refinement
from service.consistency.refined_errors import AGREED_MISMATCH
from service.pipeline import image_stage
from tests.pipeline.test_signal_loss import _prepared


def _refined(monkeypatch: pytest.MonkeyPatch, cost_after: float) -> list[np.ndarray]:
    """Two stacks through :func:`image_stage._refine_stacks` with a refinement that ends at ``cost_after``
    and leaves its slices at a quarter of the request's median mismatch (the last at the median): their
    expected errors."""
    stacks = [_prepared(), _prepared(seed=4)]
    n = [len(s.prepared.inputs) for s in stacks]
    monkeypatch.setattr(image_stage, "refine", lambda images, poses, expected, smoothed=None: Refinement(
        [p.copy() for p in poses], [np.zeros(k) for k in n], 40, 3.0, cost_after,
        [np.r_[np.full(k - 1, 0.25), 1.0] for k in n], [np.full(k, 0.5) for k in n]))
    outs = [SimpleNamespace(poses=np.repeat(np.eye(4)[None], k, 0), expected_error_mm=np.full(k, 4.0),
                            inconsistent=np.zeros(k, bool), pooled=None, fit=SimpleNamespace(placement_sd_mm=1.0),
                            image_consistency=None) for k in n]
    image_stage._refine_stacks(stacks, outs, [np.ones(k, bool) for k in n], [0, 1], [])
    return [o.expected_error_mm for o in outs]


def test_a_refinement_that_agrees_lowers_the_expected_errors_one_that_does_not_keeps_them(
        monkeypatch: pytest.MonkeyPatch) -> None:
    agreeing = _refined(monkeypatch, AGREED_MISMATCH / 10)
    disagreeing = _refined(monkeypatch, AGREED_MISMATCH * 2)
    assert all((e[:-1] < 2.0).all() for e in agreeing)                   # well below the stage's 4 mm
    assert all((e >= 4.0).all() for e in disagreeing)                    # never below the stage's
