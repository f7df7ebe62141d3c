"""``GET /v1/models`` describes each model as the service runs it."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

from service.inference.model_file import ModelInfo
from service.inference.registry import ModelRegistry
from tests.inference.test_model_file import META


def test_the_seed_described_is_the_one_the_model_runs_with() -> None:
    """A file with draw inputs but no ``mc_seed`` field runs with the default seed: that seed is
    described, not null (null means every call draws afresh)."""
    info = ModelInfo.from_metadata(META, "s")
    fixed = SimpleNamespace(info=info, model=SimpleNamespace(mc_seed=0))
    fresh = SimpleNamespace(info=replace(info, name="fresh"), model=SimpleNamespace(mc_seed=None))
    described = {m["name"]: m for m in ModelRegistry({"default": fixed, "fresh": fresh}).describe()}
    assert info.mc_seed is None and described["default"]["mc_seed"] == 0 and described["fresh"]["mc_seed"] is None
