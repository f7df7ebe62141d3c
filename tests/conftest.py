"""Shared fixtures: the location of ``../shared/data`` and a skip when it is absent; every test's
job store in a folder of the test run's, never the user's ``~/.svrnet``; the process's umask as
each test found it. The tests run numpy's and scipy's BLAS on one thread, as every process of the
service runs its stages (``SVRNET_BLAS_THREADS``)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from service.core.threads import limit_blas_threads

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
ATLAS_DIR = SHARED_DATA / "fetal_atlas"
limit_blas_threads(1)


@pytest.fixture(autouse=True)
def own_job_store(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """``SVRNET_DATA_DIR`` for apps built from default settings: a server of the user's on the
    default store keeps its jobs (a test app's start would otherwise find the store taken)."""
    monkeypatch.setenv("SVRNET_DATA_DIR", str(tmp_path_factory.mktemp("svrnet-data")))


@pytest.fixture(autouse=True)
def kept_umask() -> None:
    """A console command's start sets the umask (``load_settings``); the tests after it keep their own."""
    before = os.umask(0o022)
    os.umask(before)
    yield
    os.umask(before)


@pytest.fixture(scope="session")
def atlas_dir() -> Path:
    """``../shared/data/fetal_atlas``; skips the test when the shared data are not beside the repo."""
    if not (ATLAS_DIR / "crl_sta").is_dir():
        pytest.skip(f"needs the shared atlas data at {ATLAS_DIR} (absent on this checkout)")
    return ATLAS_DIR
