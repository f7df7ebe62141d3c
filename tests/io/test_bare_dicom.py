"""DICOM data sets without the file preamble (older archives, some exports) are read as the DICOM
files they would be, alone and as a ZIP's members, in both encodings, with their elements counted
before pydicom reads any; a raw array that starts like one is not taken for one."""

from __future__ import annotations

import struct
import zipfile
from pathlib import Path

import numpy as np
import pydicom
import pytest
from pydicom.filebase import DicomBytesIO
from pydicom.filewriter import write_dataset

from service.core.errors import PayloadTooLarge, UnsupportedFile
from service.io.bare_dicom import as_part10
from service.io.dicom_structure import ITEM, MAX_ELEMENTS, UNDEFINED
from service.io.readers import read_upload, sniff
from tests.support.corpus import dicom


def _bare(part10: bytes, implicit: bool) -> bytes:
    """The data set of the DICOM file ``part10`` alone, written again in implicit or explicit VR."""
    out = DicomBytesIO()
    out.is_little_endian, out.is_implicit_VR = True, implicit
    write_dataset(out, pydicom.dcmread(DicomBytesIO(part10)))
    return out.getvalue()


def _same(a, b) -> None:  # noqa: ANN001 - two Volumes
    np.testing.assert_array_equal(a.array, b.array)
    np.testing.assert_allclose(a.affine, b.affine, atol=1e-9)
    assert a.slice_thickness_mm == b.slice_thickness_mm


def test_a_bare_data_set_is_read_as_its_dicom_file_is(tmp_path: Path) -> None:
    """Without the preamble but with its file-meta group, or without both in either encoding: the
    same voxels and the same geometry as the DICOM file."""
    pixels = np.random.default_rng(0).integers(0, 1000, (5, 8, 10)).astype(np.uint16)
    full = dicom(pixels)
    (tmp_path / "full.dcm").write_bytes(full)
    reference = read_upload(tmp_path / "full.dcm", "full.dcm")
    variants = {"meta.dcm": full[132:], "implicit.dcm": _bare(full, True), "explicit.dcm": _bare(full, False)}
    for name, data in variants.items():
        (tmp_path / name).write_bytes(data)
        assert sniff(tmp_path / name) == "bare-dicom", name
        _same(read_upload(tmp_path / name, name), reference)


def test_a_zip_of_bare_data_sets_is_read_as_the_series_it_holds(tmp_path: Path) -> None:
    slices = [np.full((8, 10), 100 + 7 * k, np.uint16) for k in range(4)]
    files = [dicom(p, k) for k, p in enumerate(slices)]
    with zipfile.ZipFile(tmp_path / "new.zip", "w") as z:
        for k, data in enumerate(files):
            z.writestr(f"IM{k:04d}.dcm", data)
    with zipfile.ZipFile(tmp_path / "old.zip", "w") as z:
        z.writestr("readme.txt", "exported 1999")
        for k, data in enumerate(files):          # the encodings mixed, as an archive merged from two
            z.writestr(f"IM{k:04d}", _bare(data, implicit=k % 2 == 0))
    old, new = read_upload(tmp_path / "old.zip", "old.zip"), read_upload(tmp_path / "new.zip", "new.zip")
    assert old.array.shape == (10, 8, 4)
    _same(old, new)


def test_a_bare_data_set_is_counted_before_pydicom_reads_it(tmp_path: Path) -> None:
    """A few hundred KB of empty sequence items would cost pydicom gigabytes: refused (413) by name."""
    start = struct.pack("<HH2sH", 8, 0x16, b"UI", 6) + b"1.2.3\0"
    items = struct.pack("<HH2sHI", 8, 0x1140, b"SQ", 0, UNDEFINED) + struct.pack("<HHI", 0xFFFE, ITEM, 0) * MAX_ELEMENTS
    bomb = tmp_path / "bomb.dcm"
    bomb.write_bytes(start + items)
    assert sniff(bomb) == "bare-dicom"
    with pytest.raises(PayloadTooLarge, match=r"bomb\.dcm: a DICOM dataset of more than"):
        as_part10(bomb, tmp_path / "out.dcm", "bomb.dcm")
    with pytest.raises(PayloadTooLarge, match=r"bomb\.dcm"):
        read_upload(bomb, "bomb.dcm")


def test_a_bare_data_set_without_pixels_is_named(tmp_path: Path) -> None:
    empty = tmp_path / "report.dcm"
    empty.write_bytes(struct.pack("<HH2sH", 8, 0x5, b"CS", 10) + b"ISO_IR 100" +
                      struct.pack("<HH2sH", 8, 0x16, b"UI", 6) + b"1.2.3\0")
    assert sniff(empty) == "bare-dicom"
    with pytest.raises(UnsupportedFile, match=r"report\.dcm: a DICOM file without pixel data"):
        read_upload(empty, "report.dcm")


def test_bytes_08_00_at_a_files_start_alone_are_not_called_a_bare_dicom(tmp_path: Path) -> None:
    """A raw array that starts with the number 8 (little-endian) is an unknown format, alone or as a ZIP's
    member, not a DICOM data set without its preamble."""
    raw = tmp_path / "raw.bin"
    raw.write_bytes(np.array([8, 16, 300, 7, 2048, 5, 0, 12] * 32, "<u4").tobytes())
    assert sniff(raw) == "unknown"
    with pytest.raises(UnsupportedFile, match=r"raw\.bin: not a NIfTI"):
        read_upload(raw, "raw.bin")
    with zipfile.ZipFile(tmp_path / "raw.zip", "w") as z:
        z.writestr("IM0000", raw.read_bytes())
    with pytest.raises(UnsupportedFile, match=r"raw\.zip: the ZIP archive holds no DICOM series"):
        read_upload(tmp_path / "raw.zip", "raw.zip")


def test_a_bare_data_set_cut_inside_an_element_header_is_a_415_and_a_full_disk_a_507(tmp_path: Path,
                                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """The element walk stops where a long VR's length is cut short (pydicom's reading then names the
    file); a disk that fills while the data set is copied is the server's 507, not the file's 415."""
    import errno
    import io

    from service.core.errors import InsufficientStorage
    from service.io import readers
    from service.io.dicom_structure import check_structure

    cut = struct.pack("<HH2sH", 8, 0x16, b"UI", 6) + b"1.2.3\0" + struct.pack("<HH2sH", 8, 0x17, b"OB", 0) + b"\x01"
    check_structure(io.BytesIO(cut), "cut.dcm", False, True)              # no struct.error
    (tmp_path / "cut.dcm").write_bytes(cut)
    with pytest.raises(UnsupportedFile, match=r"cut\.dcm"):
        read_upload(tmp_path / "cut.dcm", "cut.dcm")

    def full(*args: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(readers, "as_part10", full)
    (tmp_path / "old.dcm").write_bytes(_bare(dicom(np.full((2, 8, 8), 100, np.uint16)), True))
    with pytest.raises(InsufficientStorage):
        read_upload(tmp_path / "old.dcm", "old.dcm")
