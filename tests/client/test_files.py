"""The client's files are written whole or not at all: a failed write leaves the file it would have
replaced as it was, and nothing beside it."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from client import files


def test_a_write_that_fails_leaves_the_earlier_file_and_no_partial_one(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    target = tmp_path / "poses.json"
    target.write_text('{"earlier": true}')

    def disk_full(*_: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", disk_full)
    with pytest.raises(OSError):
        files.write_whole(target, b'{"later": tru')
    assert target.read_text() == '{"earlier": true}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses.json"]
