"""The evaluation scans' download: pinned files checked, an uncompressed file gzipped, nothing partial left."""

from __future__ import annotations

import gzip
import hashlib
import io
from pathlib import Path

import pytest

from tools import fetch_real_scan


def _serve(monkeypatch: pytest.MonkeyPatch, files: dict[str, bytes]) -> None:
    def urlopen(url: str, timeout: float) -> io.BytesIO:  # noqa: ARG001
        return io.BytesIO(files[url.rsplit("/", 1)[-1]])
    monkeypatch.setattr(fetch_real_scan.urllib.request, "urlopen", urlopen)


def test_a_pinned_uncompressed_file_is_written_gzipped(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    data = b"\x5c\x01\x00\x00" + bytes(400)
    spec = {"repository": "o/r", "commit": "c", "files": {"s.nii.gz": "d/s.nii"},
            "sha256": {"s.nii.gz": hashlib.sha256(data).hexdigest()[:16]}}
    monkeypatch.setitem(fetch_real_scan.SCANS, "test_scan", spec)
    _serve(monkeypatch, {"s.nii": data})
    folder = fetch_real_scan.fetch(tmp_path, "test_scan")
    assert gzip.decompress((folder / "s.nii.gz").read_bytes()) == data
    assert not list(folder.glob("*.part"))


def test_a_download_that_differs_from_the_pinned_file_is_refused(monkeypatch: pytest.MonkeyPatch,
                                                                 tmp_path: Path) -> None:
    spec = {"repository": "o/r", "commit": "c", "files": {"s.nii.gz": "d/s.nii.gz"}, "sha256": {"s.nii.gz": "0" * 16}}
    monkeypatch.setitem(fetch_real_scan.SCANS, "test_scan", spec)
    _serve(monkeypatch, {"s.nii.gz": b"not the pinned file"})
    with pytest.raises(SystemExit, match="differs"):
        fetch_real_scan.fetch(tmp_path / "data", "test_scan")
    assert not (tmp_path / "data").exists()                          # no file, and no empty folder either


def test_no_network_is_one_line_naming_the_file_and_leaves_no_empty_folder(monkeypatch: pytest.MonkeyPatch,
                                                                             tmp_path: Path) -> None:
    def offline(url: str, timeout: float) -> io.BytesIO:  # noqa: ARG001
        raise fetch_real_scan.urllib.error.URLError(OSError(-2, "Name or service not known"))
    spec = {"repository": "o/r", "commit": "c", "files": {"s.nii.gz": "d/s.nii.gz"}, "sha256": {"s.nii.gz": "0" * 16}}
    monkeypatch.setitem(fetch_real_scan.SCANS, "test_scan", spec)
    monkeypatch.setattr(fetch_real_scan.urllib.request, "urlopen", offline)
    with pytest.raises(SystemExit, match=r"s.nii.gz: could not be downloaded from raw.githubusercontent.com .*not known"):
        fetch_real_scan.fetch(tmp_path / "data" / "extra", "test_scan")
    assert not (tmp_path / "data").exists()                          # nor the folders made above it
