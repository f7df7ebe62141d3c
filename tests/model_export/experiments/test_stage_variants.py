"""The stage-variants experiment's pieces of logic: overrides that are put back, the frame-free
error against an offset simulated here, and the model's calibration over a cache's."""

from __future__ import annotations

import numpy as np

import service.consistency.stack_fit as stack_fit
import service.pipeline.predict as pipeline
from model_export.experiments.stage_variants import calibrated_as, frame_free, overridden, requests
from model_export.packaging import CALIBRATION
from service.geometry import se3
from service.geometry.twin import DEFAULT_PLANE_X_MM


def test_overrides_apply_and_are_put_back() -> None:
    k, refine = stack_fit.OUTLIER_K, pipeline.refine
    saved = overridden("consistency.stack_fit.OUTLIER_K=2.0; refine:noise=0.1")
    assert stack_fit.OUTLIER_K == 2.0 and pipeline.refine.keywords == {"noise": 0.1}
    for target, name, value in saved:
        setattr(target, name, value)
    assert stack_fit.OUTLIER_K == k and pipeline.refine is refine
    assert overridden("base") == []


def test_a_common_offset_is_frame_free_and_a_slice_error_is_not() -> None:
    """Poses all moved by one rigid map score 0 frame-free (they are that far from the truth); one slice
    moved on its own keeps its move."""
    rng = np.random.default_rng(1)
    truth = se3.exp(np.concatenate([rng.normal(0, 0.3, (12, 3)), rng.normal(0, 15, (12, 3))], axis=1))
    truth[:, 0, 3] += 30.0                                        # away from the mid-sagittal plane: no twin nearer
    offset = se3.exp(np.array([0.04, -0.03, 0.02, 2.0, -1.0, 1.5]))
    moved = offset @ truth
    assert frame_free(moved, truth, DEFAULT_PLANE_X_MM).max() < 1e-6
    moved[3] = moved[3] @ se3.exp(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 6.0]))
    left = frame_free(moved, truth, DEFAULT_PLANE_X_MM)
    assert left[3] > 4.0 and np.median(left) < 1.0


def test_alone_sends_each_stack_as_its_own_request() -> None:
    prepared, parts = ["ax", "cor", "sag"], [1, 2, 3]
    assert requests(prepared, parts, alone=False) == [(prepared, parts)]
    assert requests(prepared, parts, alone=True) == [(["ax"], [1]), (["cor"], [2]), (["sag"], [3])]


def test_a_caches_info_takes_the_models_calibration_and_keeps_the_rest() -> None:
    from dataclasses import replace

    from service.inference.model_file import ModelInfo

    cached = ModelInfo("m", "1", "compact", "grid", 96, 1.25, 48.0, 0.25, "atlas", "", "old-sha")
    model = replace(cached, sha256="new-sha", variance_threshold=485.2, twin_risk_logit=(-1.2, -0.16),
                    expected_error_floor_mm=2.1, max_expected_error_mm=4.2)
    judged = calibrated_as(cached, model)
    assert all(getattr(judged, k) == getattr(model, k) for k in CALIBRATION)
    assert judged.sha256 == "old-sha" and judged.variance_threshold == 485.2
