"""Fixtures of the client's tests: no ambient server or key, recorded sleeps, a small stack and its mask."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import client.transport as client_transport
from service.io.volume import Volume, write_volume


@pytest.fixture(autouse=True)
def _no_ambient_config(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("SVRNET_API_KEY", raising=False)
    monkeypatch.delenv("SVRNET_SERVER", raising=False)


@pytest.fixture
def no_sleep(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """Record the client's retry/poll sleeps instead of sleeping."""
    slept: list[float] = []
    monkeypatch.setattr(client_transport, "sleep", slept.append)
    return slept


@pytest.fixture
def stack_file(tmp_path: Path) -> Path:
    data = np.random.default_rng(0).random((24, 24, 6)).astype(np.float32) * 100
    path = tmp_path / "stack.nii.gz"
    write_volume(Volume(data, np.diag([1.0, 1.0, 3.0, 1.0])), path)
    return path


@pytest.fixture
def mask_file(tmp_path: Path) -> Path:
    mask = np.zeros((24, 24, 6), np.uint8)
    mask[6:18, 6:18, :] = 1
    path = tmp_path / "stack_mask.nii.gz"
    write_volume(Volume(mask, np.diag([1.0, 1.0, 3.0, 1.0])), path)
    return path
