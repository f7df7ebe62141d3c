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


def test_threads_writing_one_file_leave_one_writer_s_bytes_whole(tmp_path: Path) -> None:
    """Each write has a partial file of its own (a name per process alone was shared by threads: their
    renames failed, and bytes of two writers could mix)."""
    import threading

    target, failures = tmp_path / "report.json", []

    def write(k: int) -> None:
        for _ in range(30):
            try:
                files.write_whole(target, str(k).encode() * 4096)
            except OSError as exc:                       # noqa: PERF203 - what the test counts
                failures.append(exc)

    threads = [threading.Thread(target=write, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not failures and len(set(target.read_bytes())) == 1
    assert [p.name for p in tmp_path.iterdir()] == ["report.json"]
