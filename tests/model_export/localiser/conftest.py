"""Shards of a phantom atlas, generated once for the localiser's training tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from model_export.localiser.dataset import generate

GRID_MM = 4.0
"""Coarse: small shards, fast tests."""


@pytest.fixture(scope="package")
def shards(phantom_atlas: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("shards")
    names = generate(out, ["STA30"], 2, "train", GRID_MM, first_seed=0, workers=1, keep_stack=True, root=phantom_atlas)
    assert sorted(names) == ["train-000000.npz", "train-000001.npz"]
    return out
