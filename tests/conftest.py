"""Shared fixtures: the location of ``../shared/data`` and a skip when it is absent."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
ATLAS_DIR = SHARED_DATA / "fetal_atlas"


@pytest.fixture(scope="session")
def atlas_dir() -> Path:
    """``../shared/data/fetal_atlas``; skips the test when the shared data are not beside the repo."""
    if not (ATLAS_DIR / "crl_sta").is_dir():
        pytest.skip(f"needs the shared atlas data at {ATLAS_DIR} (absent on this checkout)")
    return ATLAS_DIR
