"""The frame error's calibration on slice columns whose truth is known (no model, no atlas)."""

from __future__ import annotations

import numpy as np
import pytest

from model_export.calibrate_frame import calibrate, frame_metadata, markdown
from service.consistency.frame_error import frame_error_mm
from service.inference.model_file import ModelInfo

ONSET, SLOPE = 13.0, 0.5


def columns(rng: np.random.Generator, per_request: int = 60, slope: float = SLOPE) -> dict[str, np.ndarray]:
    """Requests of network error 9-30 mm whose slices' errors are their expected error (reported) and,
    above :data:`ONSET`, the request's own ``SLOPE x (sigma - ONSET)`` (not reported), each scattered
    as a 3D error's length scatters about its RMS."""
    sigma = np.repeat(rng.uniform(9.0, 30.0, 80), per_request)
    expected = rng.uniform(1.5, 4.0, sigma.size)
    rms = np.hypot(expected, slope * np.maximum(sigma - ONSET, 0.0))
    ed = rms * np.linalg.norm(rng.normal(size=(sigma.size, 3)), axis=1) / np.sqrt(3.0)
    return {"ed": ed, "expected": expected, "sigma": sigma}


def test_the_frame_error_the_slices_lack_is_found_again_and_read_back_by_the_service() -> None:
    cols = columns(np.random.default_rng(0))
    out = calibrate(cols)
    onset, slope = out["frame_error"]
    assert abs(onset - ONSET) <= 2.0 and abs(slope - SLOPE) <= 0.25 * SLOPE, out
    info = ModelInfo.from_metadata({"name": "m", "version": "1", "backbone": "compact", "label_type": "grid",
                                    "input_size": "96", "pixel_spacing_mm": "1.25", "variance_threshold": "1",
                                    **frame_metadata(out)}, "s")
    extra = frame_error_mm(cols["sigma"], info.frame_error)
    for lo, hi in ((18.0, 22.0), (22.0, 26.0), (26.0, 31.0)):
        g = (cols["sigma"] >= lo) & (cols["sigma"] < hi)
        before = float(np.median(cols["ed"][g] / cols["expected"][g]))
        after = float(np.median(cols["ed"][g] / np.hypot(cols["expected"][g], extra[g])))
        assert before > 1.3 * out["clean_median_ratio"] and after == pytest.approx(out["clean_median_ratio"], rel=0.15)
    assert "| request's network error" in markdown(out)


def test_a_network_whose_frame_error_does_not_grow_gains_little() -> None:
    out = calibrate(columns(np.random.default_rng(1), slope=0.0))
    assert float(frame_error_mm(30.0, tuple(out["frame_error"]))) < 1.0, out


def test_without_requests_under_the_reference_error_nothing_is_fitted() -> None:
    cols = columns(np.random.default_rng(2))
    far = cols["sigma"] >= 14.0
    with pytest.raises(ValueError, match="reference"):
        calibrate({k: v[far] for k, v in cols.items()})
