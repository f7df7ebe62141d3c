"""The accept flags' calibration on slice columns whose truth is known (no model, no atlas)."""

from __future__ import annotations

import numpy as np

from model_export.calibrate_acceptance import MAX_BAD_ACCEPTED, accepted, calibrate, rates


def level(rng: np.random.Generator, n: int, scale: float, floor: float) -> dict[str, np.ndarray]:
    """Slices whose error is the floor (shared, unseen by the stages) plus their own, which their
    expected error reports; a few have another reason to be rejected."""
    own = rng.uniform(0.5, 2.0, n) * scale
    error = np.sqrt(own ** 2 + floor ** 2) * np.abs(rng.normal(1.0, 0.15, n))
    reason = np.where(rng.random(n) < 0.05, "inconsistent_with_stack", "")
    return {"ed": error, "ed_min": error.copy(), "expected": own, "variance": rng.uniform(10, 100, n),
            "reason": reason}


def test_the_floor_makes_the_expected_error_honest_and_the_limit_keeps_bad_slices_out() -> None:
    rng = np.random.default_rng(0)
    by_level = {"mild": level(rng, 600, 1.0, 2.0), "moderate": level(rng, 600, 3.0, 2.0),
                "jumps": level(rng, 600, 5.0, 2.0)}
    out = calibrate(by_level)
    assert 1.5 <= out["expected_error_floor_mm"] <= 2.5                       # the unseen 2 mm found again
    assert all(0.8 <= v["rms_ed_over_rms_expected"] <= 1.25 for v in out["levels"].values()), out["levels"]
    assert out["levels"]["mild"]["rms_ed_over_rms_expected_before"] > 1.25    # and needed
    assert out["limit_meets_target"]
    assert all(v["bad_accepted"] <= MAX_BAD_ACCEPTED for k, v in out["levels"].items() if v["bad_slices"]), out["levels"]
    for k, c in by_level.items():                                              # nothing with another reason passes
        ok = accepted(c, out["expected_error_floor_mm"], out["variance_threshold"], out["max_expected_error_mm"])
        assert not ok[c["reason"] != ""].any()
        assert rates(c, ok)["good_accepted"] > 0.5, k
    good_variance = np.concatenate([c["variance"][c["ed"] < 5] for c in by_level.values()])
    assert (good_variance <= out["variance_threshold"]).mean() >= 0.99         # good poses pass the variance
    assert set(out["trade_off"]) == {"3", "4", "5", "6", "8"}
