"""Phantom atlas: small synthetic 'brains' laid out like ../shared/data/fetal_atlas (fixed seeds)."""

from __future__ import annotations

from pathlib import Path

import pytest

from model_export.atlas import VALIDATION_VOLUMES
from service.io.volume import Volume, write_volume
from tests.support.phantoms import phantom_brain


@pytest.fixture(scope="session")
def phantom_atlas(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with crl_sta/ and spina_bifida_cc0/ phantom volumes (validation names included)."""
    root = tmp_path_factory.mktemp("phantom_atlas")
    names = [("crl_sta", n) for n in VALIDATION_VOLUMES if n.startswith("STA")]
    names += [("spina_bifida_cc0", n) for n in VALIDATION_VOLUMES if n.startswith("SB")]
    names += [("crl_sta", "STA30"), ("spina_bifida_cc0", "SB_GA27_operated")]
    for seed, (folder, name) in enumerate(names):
        (root / folder).mkdir(exist_ok=True)
        img, mask, aff = phantom_brain(seed)
        write_volume(Volume(img, aff), root / folder / f"{name}_T2.nii.gz")
        write_volume(Volume(mask, aff), root / folder / f"{name}_mask.nii.gz")
    return root


@pytest.fixture
def pose_model_copy(tmp_path: Path) -> Path:
    """The shipped default pose model copied to ``tmp_path/model.onnx``: a file the commands that take
    an exported model accept (and may write metadata into)."""
    import shutil

    from service.core.settings import DEFAULT_MODELS_DIR

    return Path(shutil.copyfile(DEFAULT_MODELS_DIR / "default" / "model.onnx", tmp_path / "model.onnx"))
