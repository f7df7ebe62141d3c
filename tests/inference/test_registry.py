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
