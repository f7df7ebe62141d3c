"""App fixtures: an oracle estimator that knows the simulated truth, a tiny real exported model."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient

from model_export.export import build_metadata, export_onnx, fix_draws
from model_export.model import SVRNet
from service.core.settings import Settings
from service.inference.estimator import OnnxPoseEstimator, PoseEstimate
from service.inference.model_file import ModelInfo, load_model
from service.inference.registry import ModelRegistry
from service.io.volume import Volume, write_volume
from service.main import create_app
from tests.support.local_client import LocalClient
from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine
from tests.support.scratch import job_store_dir

INFO = ModelInfo(name="oracle", version="0", backbone="oracle", label_type="anchor", input_size=64,
                 pixel_spacing_mm=2.0, variance_threshold=10.0, dropout_p=0.5, atlas_id="phantom",
                 trained_on="-", sha256="0" * 64)


class OracleEstimator:
    """Returns, for the k-th slice it is given, the k-th pose of ``truth`` (set by each test), with an
    MC spread of ``spread_mm`` (0: certain)."""

    info = INFO

    def __init__(self) -> None:
        self.truth: np.ndarray | None = None
        self.seen: np.ndarray | None = None
        self.spread_mm = 0.0

    def estimate(self, inputs: np.ndarray, mc_samples: int) -> PoseEstimate:
        assert self.truth is not None and len(self.truth) == len(inputs), "truth and slices out of step"
        self.seen = inputs
        n = len(inputs)
        return PoseEstimate(self.truth.copy(), np.full(n, 1.0), np.zeros(n, bool), spread_mm=np.full(n, self.spread_mm))


@pytest.fixture(scope="session")
def tiny_model_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small exported SVRnet (random weights, 64 px at 2 mm) with real MC dropout, its draws fed by
    the service as a shipped model's are."""
    torch.manual_seed(0)
    model = SVRNet("compact", 0.25, "anchor", 64, hidden=32).eval()
    model.set_label_normalisation(torch.randn(50, 9) * 40)
    meta = build_metadata(model, name="tiny", version="0.0.1", pixel_mm=2.0, variance_threshold=1e9,
                          atlas_id="phantom", training_data="none", licences="n/a")
    path = export_onnx(model, tmp_path_factory.mktemp("models") / "tiny" / "model.onnx", meta)
    fix_draws(path)
    return path


def make_client(registry: ModelRegistry, **settings: object) -> TestClient:
    """A TestClient of the app with ``registry``; the job store goes to a fresh temporary folder."""
    settings.setdefault("data_dir", job_store_dir())
    return LocalClient(create_app(Settings(**settings), registry=registry), raise_server_exceptions=False)


@pytest.fixture
def oracle() -> OracleEstimator:
    return OracleEstimator()


@pytest.fixture
def oracle_client(oracle: OracleEstimator) -> Iterator[TestClient]:
    with make_client(ModelRegistry({"default": oracle})) as client:
        yield client


@pytest.fixture
def real_client(tiny_model_path: Path) -> Iterator[TestClient]:
    registry = ModelRegistry({"default": OnnxPoseEstimator(load_model(tiny_model_path))})
    with make_client(registry) as client:
        yield client


@pytest.fixture(scope="session")
def phantom_files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, int]:
    """A phantom stack of 16 slices and its mask, as NIfTI files."""
    brain = phantom_brain(3)
    shape = (48, 48, 16)
    aff = stack_affine(2, np.eye(3), 1.5, 3.5, shape)
    g = np.broadcast_to(np.eye(4), (16, 4, 4))
    img, msk = acquire_stack(*brain, aff, shape, 2, g)
    d = tmp_path_factory.mktemp("phantom_stack")
    write_volume(Volume(img * 3.0 + 20.0, aff), d / "stack.nii.gz")
    write_volume(Volume(msk.astype(np.uint8), aff), d / "mask.nii.gz")
    return d / "stack.nii.gz", d / "mask.nii.gz", 16
