"""The stage-variants experiment's pieces of logic: overrides that are put back, the frame-free
error against an offset simulated here, and the model's calibration over a cache's."""

from __future__ import annotations

import numpy as np

import service.consistency.stack_fit as stack_fit
import service.pipeline.predict as pipeline
from service.pipeline import image_stage
from model_export.experiments.stage_variants import calibrated_as, frame_free, overridden, requests
from model_export.packaging import CALIBRATION
from service.geometry import se3
from service.geometry.twin import DEFAULT_PLANE_X_MM


def test_overrides_apply_and_are_put_back() -> None:
    k, refine = stack_fit.OUTLIER_K, image_stage.refine
    saved = overridden("consistency.stack_fit.OUTLIER_K=2.0; refine:noise=0.1")
    assert stack_fit.OUTLIER_K == 2.0 and image_stage.refine.keywords == {"noise": 0.1}
    for target, name, value in saved:
        setattr(target, name, value)
    assert stack_fit.OUTLIER_K == k and image_stage.refine is refine
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


def test_the_cached_slices_columns_are_written_as_calibrate_acceptance_reads_them(tmp_path, monkeypatch) -> None:  # noqa: ANN001
    """``--columns``: each slice's error, expected error and reason under ``<level>/<column>``, measured
    with the calibration switched off; ``level_columns`` keeps the slices with brain."""
    from dataclasses import replace
    from types import SimpleNamespace

    from model_export.calibrate_acceptance import level_columns
    from model_export.experiments.stage_variants import write_columns
    from service.inference.model_file import ModelInfo

    truth = np.repeat(np.eye(4)[None], 4, axis=0)
    truth[:, 0, 3] = 30.0
    poses = truth.copy()
    poses[:, 1, 3] += [1.0, 2.0, 12.0, 0.0]                        # E.D. 1, 2, 12 mm; the last slice empty
    seen = {}

    def predict_from_estimates(prepared, parts, info, threshold):  # noqa: ANN001, ANN202
        seen["info"] = info
        fit = SimpleNamespace(decidable=True)
        p = SimpleNamespace(poses=SimpleNamespace(poses=poses, expected_error_mm=np.array([1.5, 2.5, np.nan, 3.0]), fit=fit),
                            estimate=SimpleNamespace(variance=np.array([1.0, 2.0, 3.0, np.nan])),
                            reasons=[None, None, "high_variance", "empty"],
                            prepared=SimpleNamespace(prepared=SimpleNamespace(mask_pixels=np.array([50, 50, 50, 0]))))
        return [p], {}

    monkeypatch.setattr(pipeline, "predict_from_estimates", predict_from_estimates)
    info = replace(ModelInfo("m", "1", "compact", "grid", 96, 1.25, 48.0, 0.25, "atlas", "", "sha"),
                   expected_error_floor_mm=0.9, max_expected_error_mm=4.5, twin_risk_logit=(-1.2, -0.1))
    write_columns(info, [("moderate", ["stack"], ["estimate"], [truth])], tmp_path / "b.npz")
    assert seen["info"].expected_error_floor_mm == 0.0 and seen["info"].max_expected_error_mm is None
    assert seen["info"].twin_risk_logit is None
    cols = level_columns(tmp_path / "b.npz", ("moderate", "jumps"))["moderate"]
    np.testing.assert_allclose(cols["ed"], [1.0, 2.0, 12.0], atol=1e-9)
    assert np.isnan(cols["expected"][2]) and cols["reason"].tolist() == ["", "", "high_variance"]
    assert cols["decidable"].all() and (cols["twin_mm"] > 0).all()

