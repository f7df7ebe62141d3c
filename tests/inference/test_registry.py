"""``GET /v1/models`` describes each model as the service runs it."""

from __future__ import annotations

import shutil
from pathlib import Path

import onnx

from model_export.export import metadata_of, set_metadata
from service.inference.estimator import OnnxPoseEstimator
from service.inference.model_file import DEFAULT_MC_SEED, load_model
from service.inference.registry import ModelRegistry


def test_the_seed_described_is_the_one_the_model_runs_with(tiny_model_path: Path, tmp_path: Path) -> None:
    """A file with draw inputs but no ``mc_seed`` field runs with the default seed: that seed is
    described, not null (null means every call draws afresh)."""
    path = tmp_path / "model.onnx"
    shutil.copy(tiny_model_path, path)
    proto = onnx.load(str(path))
    set_metadata(proto, {k: v for k, v in metadata_of(proto).items() if k != "mc_seed"})
    onnx.save(proto, str(path))
    model = load_model(path)
    assert "mc_seed" not in model.info.metadata and model.draw_inputs
    [described] = ModelRegistry({"default": OnnxPoseEstimator(model)}).describe()
    assert described["mc_seed"] == model.mc_seed == DEFAULT_MC_SEED


def test_a_job_is_told_the_file_each_served_model_was_and_a_stand_in_is_no_file(tiny_model_path: Path,
                                                                                tmp_path: Path) -> None:
    """A registry of the models folder names each model's file by its sha256 (what a job's submission
    records, for its worker to load that file and no other), and whether its card is there; a
    registry of stand-ins (tests) names none."""
    (tmp_path / "next").mkdir()
    shutil.copy(tiny_model_path, tmp_path / "next" / "model.onnx")
    (tmp_path / "next" / "card.md").write_text("# card\n")
    served = ModelRegistry.from_directory(tmp_path, default_name="next")
    assert served.served_sha256("default") == load_model(tiny_model_path).info.sha256
    assert served.describe()[0]["card"] is True and served.describe()[0]["name"] == "next"
    stand_in = ModelRegistry({"next": served.get("next")}, default_name="next")
    assert stand_in.served_sha256("next") is None and stand_in.describe()[0]["card"] is False
