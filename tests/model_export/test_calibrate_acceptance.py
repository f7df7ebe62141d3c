"""The accept flags' calibration on slice columns whose truth is known (no model, no atlas)."""

from __future__ import annotations

import numpy as np
import pytest

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


def with_twins(rng: np.random.Generator, columns: dict[str, np.ndarray], logit: tuple[float, float]) -> dict[str, np.ndarray]:
    """``columns`` whose slices sit on their twin with the chance ``logit`` gives at their distance to
    it (0-60 mm) in the consistent stacks, and always within 10 mm of it in the others (15 %, the
    network's own branch): those slices' truth error grows by that distance, unseen by their
    expected error."""
    n = len(columns["ed"])
    d = rng.uniform(0.0, 60.0, n)
    decidable = rng.random(n) < 0.85
    on = rng.random(n) < np.where(decidable, 1.0 / (1.0 + np.exp(-(logit[0] + logit[1] * d))), d < 10.0)
    ed = np.where(on, np.hypot(columns["ed"], d), columns["ed"])
    return {**columns, "ed": ed, "ed_min": np.minimum(ed, columns["ed"]), "twin_mm": d, "decidable": decidable}


def test_the_twin_risk_is_found_again_and_lets_the_limit_pass_more_good_slices() -> None:
    """Slices of consistent stacks near the mid-sagittal plane that sit on their twin (a logistic in
    their distance to it) are bad slices with a small expected error. The calibration finds the
    logistic again from those stacks alone (the others' twins follow no such curve); with it those
    slices' expected errors grow, the limit keeps them out and passes more good slices than a
    calibration that does not know the twin's distance."""
    rng = np.random.default_rng(1)
    logit = (-1.0, -0.12)
    by_level = {k: with_twins(rng, level(rng, 3000, s, 2.0), logit) for k, s in (("mild", 1.0), ("moderate", 2.0), ("jumps", 2.5))}
    out = calibrate(by_level)
    a, b = out["twin_risk_logit"]
    assert abs(a - logit[0]) < 0.3 and abs(b - logit[1]) < 0.03, out["twin_risk_logit"]
    assert out["limit_meets_target"]
    blind = calibrate({k: {c: v for c, v in cols.items() if c not in ("twin_mm", "decidable")} for k, cols in by_level.items()})
    assert blind["twin_risk_logit"] is None
    for k in by_level:
        assert out["levels"][k]["bad_accepted"] <= MAX_BAD_ACCEPTED
        assert out["levels"][k]["good_accepted"] > blind["levels"][k]["good_accepted"] + 0.02, (k, out["levels"][k], blind["levels"][k])


def test_a_level_with_a_handful_of_bad_slices_does_not_decide_the_limit() -> None:
    """Mild motion with three bad slices, one of them with a small expected error: it alone would
    pull the limit down to where a third of the bad slices are rejected; it is reported, not judged."""
    from model_export.calibrate_acceptance import BAD_MM, MIN_BAD_SLICES

    rng = np.random.default_rng(2)
    by_level = {"mild": level(rng, 600, 1.0, 2.0), "moderate": level(rng, 600, 6.0, 2.0),
                "jumps": level(rng, 600, 6.0, 2.0)}
    mild = by_level["mild"]
    mild["ed"][:3], mild["ed_min"][:3], mild["expected"][:3], mild["reason"][:3] = 12.0, 12.0, [1.0, 6.0, 8.0], ""
    assert (mild["ed"] > BAD_MM).sum() == 3 < MIN_BAD_SLICES
    out = calibrate(by_level)
    assert out["judged_levels"] == ["moderate", "jumps"] and out["limit_meets_target"]
    assert out["levels"]["mild"]["bad_accepted"] > MAX_BAD_ACCEPTED                  # reported as it is
    alone = calibrate({"mild": mild})
    assert alone["judged_levels"] == ["mild"] and alone["max_expected_error_mm"] < out["max_expected_error_mm"]


def test_the_columns_of_several_runs_are_pooled_level_by_level(tmp_path) -> None:  # noqa: ANN001
    """``--columns`` given twice: each level's slices with brain from both files; a level one file
    lacks comes from the other alone."""
    from model_export.calibrate_acceptance import level_columns

    def write(path, levels, n, offset):  # noqa: ANN001, ANN202
        cols = {}
        for lv in levels:
            cols[f"{lv}/ed"] = np.arange(n, dtype=float) + offset
            cols[f"{lv}/expected"] = np.full(n, np.inf)
            cols[f"{lv}/mask_pixels"] = np.where(np.arange(n) % 2 == 0, 100, 0)      # every other slice has brain
            for key in ("ed_min", "variance", "twin_mm"):
                cols[f"{lv}/{key}"] = np.ones(n)
            cols[f"{lv}/reason"] = np.array([""] * n)
            cols[f"{lv}/decidable"] = np.ones(n, bool)
        np.savez(path, **cols)

    write(tmp_path / "a.npz", ("mild", "independent"), 6, 0.0)
    write(tmp_path / "b.npz", ("mild",), 4, 100.0)
    out = level_columns([tmp_path / "a.npz", tmp_path / "b.npz"], ("mild", "independent", "jumps"))
    assert set(out) == {"mild", "independent"}
    assert out["mild"]["ed"].tolist() == [0.0, 2.0, 4.0, 100.0, 102.0]
    assert out["independent"]["ed"].tolist() == [0.0, 2.0, 4.0] and np.isnan(out["mild"]["expected"]).all()
    assert level_columns(tmp_path / "b.npz", ("mild",))["mild"]["ed"].tolist() == [100.0, 102.0]


def test_a_model_that_places_no_slice_well_is_told_so_not_an_index_error() -> None:
    """A short run's model: every slice tens of mm off. The calibration says why it cannot be made."""
    rng = np.random.default_rng(3)
    far = {k: {**c, "ed": c["ed"] + 40.0, "ed_min": c.get("ed_min", c["ed"]) + 40.0}
           for k, c in {"mild": level(rng, 200, 2.0, 1.0), "moderate": level(rng, 200, 3.0, 1.0)}.items()}
    with pytest.raises(ValueError, match="none of the 400 slices lies within 5 mm"):
        calibrate(far)


def test_the_flags_are_measured_without_the_terms_calibrated_after_them() -> None:
    """A shipped model carries its noise and frame errors; calibrating its flags again measures the
    expected errors as they were first calibrated, without either (before, the frame error stayed on)."""
    from dataclasses import replace

    from model_export.calibrate_acceptance import measuring
    from tests.api.conftest import INFO

    info = replace(INFO, noise_error=(0.06, 2.0), frame_error=(9.5, 0.26), max_expected_error_mm=4.5,
                   expected_error_floor_mm=1.0, twin_risk_logit=(1.0, -2.0))
    off = measuring(info)
    assert (off.noise_error, off.frame_error, off.max_expected_error_mm, off.twin_risk_logit) == (None, None, None, None)
    assert off.expected_error_floor_mm == 0.0 and off.mc_error_scale == info.mc_error_scale
