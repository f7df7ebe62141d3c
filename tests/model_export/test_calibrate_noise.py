"""The noise error's calibration on slice columns whose truth is known (no model, no atlas)."""

from __future__ import annotations

import numpy as np
import pytest

from model_export.calibrate_noise import calibrate, fit_hinge, median_ratio, missing_error, noise_metadata
from service.inference.model_file import ModelInfo
from service.preprocess.noise import noise_error_mm

ONSET, SLOPE = 0.10, 40.0


def columns(rng: np.random.Generator, per_level: int = 400, slope: float = SLOPE) -> dict[str, np.ndarray]:
    """Stacks at input noise 0.03-0.18 whose slices' errors are their expected error (reported) and,
    above :data:`ONSET`, the noise's own ``SLOPE x (noise - ONSET)`` (not reported), each scattered
    as a 3D error's length scatters about its RMS."""
    noise = np.repeat(np.array([0.03, 0.05, 0.08, 0.10, 0.12, 0.14, 0.16, 0.18]), per_level)
    noise = noise + rng.normal(0.0, 0.004, noise.size)
    expected = rng.uniform(1.5, 4.0, noise.size)
    rms = np.hypot(expected, slope * np.maximum(noise - ONSET, 0.0))
    ed = rms * np.linalg.norm(rng.normal(size=(noise.size, 3)), axis=1) / np.sqrt(3.0)
    return {"ed": ed, "expected": expected, "input_noise": noise}


def test_the_noise_error_the_slices_lack_is_found_again() -> None:
    out = calibrate(columns(np.random.default_rng(0)))
    onset, slope = out["noise_error"]
    assert abs(onset - ONSET) <= 0.02 and abs(slope - SLOPE) <= 0.25 * SLOPE, out
    noisy = [g for g in out["groups"] if g["noise"] > 0.15]
    assert noisy and all(g["median_ratio"] > 1.2 * out["clean_median_ratio"] for g in noisy)   # and it was needed


def test_with_the_noise_error_added_every_group_stands_to_its_expected_errors_as_the_clean_ones_do() -> None:
    """Through the service's own formula (the calibration read back from the model's metadata)."""
    cols = columns(np.random.default_rng(1))
    out = calibrate(cols)
    info = ModelInfo.from_metadata({"name": "m", "version": "1", "backbone": "compact", "label_type": "grid",
                                    "input_size": "96", "pixel_spacing_mm": "1.25", "variance_threshold": "1",
                                    **noise_metadata(out)}, "s")
    extra = noise_error_mm(cols["input_noise"], info.noise_error)
    for lo, hi in ((0.0, 0.09), (0.11, 0.13), (0.15, 0.17), (0.17, 1.0)):
        g = (cols["input_noise"] >= lo) & (cols["input_noise"] < hi)
        ratio = median_ratio(cols["ed"][g], cols["expected"][g], 0.0) if hi < 0.1 else \
            float(np.median(cols["ed"][g] / np.hypot(cols["expected"][g], extra[g])))
        assert ratio == pytest.approx(out["clean_median_ratio"], rel=0.12), (lo, ratio)


@pytest.mark.parametrize("seed", [2, 3, 4])
def test_a_network_as_sure_of_noisy_stacks_as_it_should_be_gains_little(seed: int) -> None:
    """Every group's slices as trusted as they should be: what the fit adds stays within the groups'
    scatter (0.8 mm on an expected error of 2.5 mm makes it 2.62 mm) up to the noisiest."""
    out = calibrate(columns(np.random.default_rng(seed), slope=0.0))
    assert float(noise_error_mm(0.18, tuple(out["noise_error"]))) < 0.8, out


def test_the_missing_error_and_the_hinge_are_what_they_say() -> None:
    assert missing_error(np.full(5, 2.0), np.full(5, 3.0), 1.0) == 0.0              # already trusted less
    assert missing_error(np.full(5, 5.0), np.full(5, 3.0), 1.0) == pytest.approx(4.0, abs=1e-6)
    noise = np.repeat([0.04, 0.08, 0.12, 0.16], 3)                   # missing 0, 0, 2 and 4 mm of 3 mm
    ed = np.hypot(3.0, np.repeat([0.0, 0.0, 2.0, 4.0], 3))
    onset, slope = fit_hinge(noise, ed, np.full(12, 3.0), [noise == v for v in (0.04, 0.08, 0.12, 0.16)], 1.0)
    assert onset == pytest.approx(0.08, abs=0.006) and slope == pytest.approx(50.0, abs=4.0)


def test_the_command_calibrates_from_kept_columns_and_writes_the_metadata_and_report(
        tmp_path, monkeypatch: pytest.MonkeyPatch, pose_model_copy) -> None:  # noqa: ANN001
    from typer.testing import CliRunner

    import model_export.spread as spread
    from model_export.cli import app

    cols = columns(np.random.default_rng(5))
    np.savez_compressed(tmp_path / "columns.npz", **cols)
    written = []
    monkeypatch.setattr(spread, "write_metadata", lambda path, updates: written.append((path, updates)))
    report = tmp_path / "noise.md"
    half = {k: v[1::2] for k, v in cols.items()}
    np.savez_compressed(tmp_path / "odd.npz", **half)
    np.savez_compressed(tmp_path / "even.npz", **{k: v[::2] for k, v in cols.items()})
    result = CliRunner().invoke(app, ["calibrate-noise", str(pose_model_copy), "--columns", str(tmp_path / "odd.npz"),
                                      "--columns", str(tmp_path / "even.npz"), "--report", str(report)])
    assert result.exit_code == 0, result.output
    pooled = {k: np.concatenate([v[1::2], v[::2]]) for k, v in cols.items()}      # two runs' slices together
    assert written == [(pose_model_copy, noise_metadata(calibrate(pooled)))]
    assert calibrate(pooled)["noise_error"] == calibrate(cols)["noise_error"]
    assert "| input noise (median) |" in report.read_text()


def test_without_clean_stacks_or_with_one_group_there_is_nothing_to_calibrate_against() -> None:
    cols = columns(np.random.default_rng(6))
    with pytest.raises(ValueError, match="clean reference"):
        calibrate({k: v[cols["input_noise"] > 0.07] for k, v in cols.items()})
    with pytest.raises(ValueError, match="fewer than two groups"):
        calibrate({k: v[cols["input_noise"] < 0.045] for k, v in cols.items()})


def test_the_noise_error_is_measured_without_the_frame_error_calibrated_after_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """The acquisitions run with the model's noise and frame errors off (before, the frame error stayed on)."""
    from dataclasses import replace
    from types import SimpleNamespace

    import model_export.calibrate_noise as calibrate_noise
    from tests.api.conftest import INFO

    seen = []

    class Seen(Exception):
        pass

    def run(stacks, estimator):  # noqa: ANN001, ANN202
        seen.append(estimator.info)
        raise Seen

    monkeypatch.setattr(calibrate_noise, "acquire", lambda *a, **k: [])
    monkeypatch.setattr(calibrate_noise, "run_acquisition", run)
    estimator = SimpleNamespace(info=replace(INFO, noise_error=(0.06, 2.0), frame_error=(9.5, 0.26)))
    with pytest.raises(Seen):
        calibrate_noise.measure(estimator, [object()], per_volume=1)
    assert seen[0].noise_error is None and seen[0].frame_error is None
    assert estimator.info.frame_error == (9.5, 0.26)                        # the caller's model keeps its own
