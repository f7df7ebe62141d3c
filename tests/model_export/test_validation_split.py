"""A model is evaluated and calibrated on the validation volumes its own run held out, and its
threshold measured on the file exported from it (a tiny random network on the phantom atlas)."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from model_export.atlas import VALIDATION_VOLUMES, validation_volumes
from model_export.model import SVRNet
from model_export.simulate import SimulationConfig

OWN_SPLIT = ["SB_GA27_operated", "STA30"]
"""The phantom atlas's two volumes outside :data:`VALIDATION_VOLUMES`: this run's held-out ones."""


@pytest.fixture(scope="module")
def own_split(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A checkpoint that trained on the fixed validation volumes and held out :data:`OWN_SPLIT`, and
    the ONNX file exported from it."""
    from model_export.packaging import export_checkpoint

    torch.manual_seed(0)
    model = SVRNet("compact", 0.25, "anchor", 48, hidden=16, dropout=0.5).eval()
    sim = SimulationConfig(size=48, pixel_mm=2.5)
    ck = {"model": model.state_dict(), "model_config": model.config, "simulation": asdict(sim), "step": 4,
          "samples_seen": 64, "train_seconds": 1.0,
          "config": {"train_volumes": list(VALIDATION_VOLUMES), "val_volumes": OWN_SPLIT, "batch": 16}}
    folder = tmp_path_factory.mktemp("own_split")
    torch.save(ck, folder / "run.pt")
    onnx_path = export_checkpoint(folder / "run.pt", folder / "model.onnx", name="own", version="0.0.1",
                                  variance_threshold=10.0, tta_views=1)
    return folder / "run.pt", onnx_path


def test_a_model_records_its_own_split_and_is_evaluated_on_it(own_split: tuple[Path, Path], phantom_atlas: Path,
                                                              tmp_path: Path) -> None:
    from model_export.evaluate import evaluate
    from service.inference.model_file import load_model

    _, onnx_path = own_split
    meta = load_model(onnx_path).info.metadata
    assert validation_volumes(meta) == OWN_SPLIT and meta["validation_volumes"] == ",".join(OWN_SPLIT)
    assert validation_volumes({"training_data": meta["training_data"]}) == OWN_SPLIT     # a file of before
    summary = evaluate(onnx_path, tmp_path / "report.md", phantom_atlas, per_volume=2, mc_samples=2)
    assert sorted(summary["per_volume"]) == OWN_SPLIT
    report = (tmp_path / "report.md").read_text()              # every pose figure against the truth and twin-min
    assert "inliers (3-MAD on twin-min G.D.)" in report and "G.D., truth / twin-min" in report
    assert summary["gd_twin_mean"] <= summary["gd_mean"] + 1e-9 and "outlier_twin_fraction" in summary


def test_the_accept_flags_and_the_noise_error_are_measured_on_the_models_own_split(
        own_split: tuple[Path, Path], phantom_atlas: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import model_export.calibrate_acceptance as acceptance
    import model_export.calibrate_noise as noise
    from model_export.cli import app

    class Measured(Exception):
        """What the stubs stop at, once they have seen the volumes."""

    seen: dict[str, list[str]] = {}

    def measure(step: str):  # noqa: ANN202
        def stub(estimator: object, volumes: list, *args: object, **kw: object) -> None:
            seen[step] = sorted(v.name for v in volumes)
            raise Measured
        return stub

    monkeypatch.setattr(acceptance, "measure", measure("acceptance"))
    monkeypatch.setattr(noise, "measure", measure("noise"))
    for command in ("calibrate-acceptance", "calibrate-noise"):
        result = CliRunner().invoke(app, [command, str(own_split[1]), "--root", str(phantom_atlas), "--no-write",
                                          "--report", str(tmp_path / "r.md")])
        assert isinstance(result.exception, Measured), result.output
    assert seen == {"acceptance": OWN_SPLIT, "noise": OWN_SPLIT}


def test_the_threshold_is_calibrated_on_the_file_as_the_service_runs_it(own_split: tuple[Path, Path],
                                                                        phantom_atlas: Path) -> None:
    """``model_file``: the statistics are the served file's (its fixed draws, through the service's
    estimator), on the checkpoint's own validation volumes; without it, the float network's in torch."""
    from model_export.calibrate import calibrate
    from model_export.train import validation_set
    from service.inference.estimator import OnnxPoseEstimator, statistics
    from service.inference.model_file import load_model

    checkpoint, onnx_path = own_split
    on_file = calibrate(checkpoint, phantom_atlas, per_volume=3, mc_samples=4, model_file=onnx_path)
    ck = torch.load(checkpoint, weights_only=False)
    val = validation_set(OWN_SPLIT, phantom_atlas, 3, seed=777, config=SimulationConfig(**ck["simulation"]))
    served = OnnxPoseEstimator(load_model(onnx_path))
    expected = statistics(served.sample_labels(val.inputs, 4), "anchor", 0.0).variance
    assert on_file["n_slices"] == 6 and on_file["measured_on"] == "model.onnx"
    assert np.allclose(on_file["variance"], expected)
    on_float = calibrate(checkpoint, phantom_atlas, per_volume=3, mc_samples=4)
    assert on_float["measured_on"].startswith("checkpoint") and not np.allclose(on_float["variance"], expected)
