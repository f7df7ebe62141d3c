"""Accept flags judge the returned pose: its expected error against ``max_expected_error_mm``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tests.api.test_predict_geometry import two_still_stacks


def _slices(body: dict) -> list[dict]:
    return [s for st in body["stacks"] for s in st["slices"]]


def test_the_expected_error_limit_flags_slices_and_is_echoed(oracle, oracle_client, tmp_path: Path) -> None:  # noqa: ANN001
    """An oracle whose MC spread says 4 mm: a limit under every slice's expected error rejects every
    slice that had brain as ``high_expected_error``; a limit above them all rejects none for it; without
    the field the model's default applies (none for this model: the field comes back null)."""
    files, truths = two_still_stacks(tmp_path)
    oracle.truth = np.concatenate(truths)
    oracle.spread_mm = 4.0
    data = {"bias_correction": "false", "mc_samples": "5", "image_consistency": "false"}
    bodies = {}
    for limit in ("0.01", "1000", None):
        r = oracle_client.post("/v1/predict", files=files, data=data | ({} if limit is None else {"max_expected_error_mm": limit}))
        assert r.status_code == 200, r.text
        bodies[limit] = r.json()
    tight = _slices(bodies["0.01"])
    expected = np.array([s["expected_error_mm"] for s in tight], dtype=float)
    judged = np.array([s["reason"] not in ("empty", "outside_atlas") for s in tight])
    assert judged.sum() > 10 and np.all(expected[judged] > 0.01)
    assert all(s["reason"] == "high_expected_error" and not s["accepted"] for s, j in zip(tight, judged) if j)
    assert bodies["0.01"]["max_expected_error_mm"] == 0.01 and bodies["1000"]["max_expected_error_mm"] == 1000.0
    loose = _slices(bodies["1000"])
    assert not any(s["reason"] == "high_expected_error" for s in loose)
    assert sum(s["accepted"] for s in loose) == judged.sum()
    assert bodies[None]["max_expected_error_mm"] is None
    assert [s["accepted"] for s in _slices(bodies[None])] == [s["accepted"] for s in loose]


def test_the_models_floor_and_limit_are_the_defaults(oracle, oracle_client, tmp_path: Path) -> None:  # noqa: ANN001
    """A model calibrated with a 3 mm floor and a 6 mm limit: every expected error includes the floor
    (sqrt(e^2 + 3^2) of what the stages said), the limit applies without the field and is echoed, and
    ``GET /v1/models`` lists it."""
    from dataclasses import replace

    files, truths = two_still_stacks(tmp_path)
    oracle.truth = np.concatenate(truths)
    oracle.spread_mm = 4.0
    data = {"bias_correction": "false", "mc_samples": "5", "image_consistency": "false"}
    plain = oracle_client.post("/v1/predict", files=files, data=data).json()
    oracle.info = replace(oracle.info, expected_error_floor_mm=3.0, max_expected_error_mm=6.0)
    body = oracle_client.post("/v1/predict", files=files, data=data).json()
    assert body["max_expected_error_mm"] == 6.0
    before = np.array([s["expected_error_mm"] for s in _slices(plain)], dtype=float)
    after = np.array([s["expected_error_mm"] for s in _slices(body)], dtype=float)
    np.testing.assert_allclose(after, np.hypot(before, 3.0), rtol=1e-6)
    for s in _slices(body):
        if s["reason"] not in ("empty", "outside_atlas", "inconsistent_with_stack"):
            assert (s["reason"] == "high_expected_error") == (s["expected_error_mm"] > 6.0)
    assert oracle_client.get("/v1/models").json()[0]["max_expected_error_mm"] == 6.0
