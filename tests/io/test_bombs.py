"""Every decoder is bounded before or while it inflates, and so is a whole request."""

from __future__ import annotations

import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest
from pydicom import uid

from service.core.errors import PayloadTooLarge, UnsupportedFile, UnusableImage
from service.io.limits import DecodeBudget
from service.io.readers import read_upload
from tests.support import corpus

MB = 2**20


def read(tmp_path: Path, data: bytes, name: str, limit_mb: float = 8, request_mb: float | None = None):  # noqa: ANN201
    path = tmp_path / "upload"
    path.write_bytes(data)
    budget = DecodeBudget(int(limit_mb * MB), int((request_mb or limit_mb) * MB))
    return read_upload(path, name, budget=budget.file(name))


def test_a_dicom_deflate_bomb_is_stopped_while_it_inflates(tmp_path: Path) -> None:
    bomb = corpus.deflate_bomb(64)                      # 64 MB of pixels in ~66 KB
    assert len(bomb) < 100_000
    tracemalloc.start()
    with pytest.raises(PayloadTooLarge, match="bomb.dcm"):
        read(tmp_path, bomb, "bomb.dcm", limit_mb=4)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 3 * 4 * MB, f"{peak / MB:.0f} MB allocated to refuse a 64 MB bomb at 4 MB"


@pytest.mark.parametrize("deflate", [True, False])
@pytest.mark.parametrize("what", ["items", "elements", "nested after the pixels"])
def test_a_dicom_dataset_of_countless_tiny_parts_is_refused_before_pydicom_builds_it(tmp_path: Path, what: str,
                                                                                     deflate: bool) -> None:
    """Empty sequence items or zero-length elements cost 8 bytes in a file and hundreds as pydicom's
    objects: a few hundred KB (tens when deflated) would take gigabytes, at any depth, before or
    after the pixel data. 413 at once, within bounded memory."""
    import struct
    import zlib

    from pydicom.filebase import DicomBytesIO
    from pydicom.filewriter import write_dataset

    from service.io import dicom_structure

    most = dicom_structure.MAX_ELEMENTS
    sequence = struct.pack("<HH2sHI", 0x0008, 0x1140, b"SQ", 0, 0xFFFFFFFF)
    end = struct.pack("<HHI", 0xFFFE, 0xE0DD, 0)
    item = struct.pack("<HHI", 0xFFFE, 0xE000, 0xFFFFFFFF)
    tiny = b"".join(struct.pack("<HH2sH", 0x0009, k + 1, b"LO", 0) for k in range(100))
    ds = corpus._dataset(8, 8, 2)
    ds.PixelData = np.zeros((2, 8, 8), np.uint16).tobytes()
    out = DicomBytesIO()
    out.is_little_endian, out.is_implicit_VR = True, False
    write_dataset(out, ds)
    if what == "items":
        body = sequence + struct.pack("<HHI", 0xFFFE, 0xE000, 0) * (most + 1) + end + out.getvalue()
    elif what == "elements":
        body = b"".join(struct.pack("<HH2sH", 0x0009 + 2 * (k // 60000), k % 60000 + 1, b"LO", 0)
                        for k in range(most + 1)) + out.getvalue()
    else:                                            # items of tiny elements, in a private sequence after the pixels
        private = struct.pack("<HH2sHI", 0x7FE1, 0x1140, b"SQ", 0, 0xFFFFFFFF)
        body = out.getvalue() + private + (item + tiny + struct.pack("<HHI", 0xFFFE, 0xE00D, 0)) * (most // 100) + end
    if deflate:
        c = zlib.compressobj(9, zlib.DEFLATED, -zlib.MAX_WBITS)
        data = corpus._file(ds, uid.DeflatedExplicitVRLittleEndian, c.compress(body) + c.flush())
    else:
        data = corpus._file(ds, uid.ExplicitVRLittleEndian, body)
    tracemalloc.start()
    with pytest.raises(PayloadTooLarge, match=f"more than {most} elements and sequence items"):
        read(tmp_path, data, "tiny.dcm", limit_mb=64, request_mb=256)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 64 * MB, peak


def test_a_file_meta_group_of_countless_elements_is_refused_before_pydicom_reads_it(tmp_path: Path) -> None:
    """pydicom reads the file-meta group whole before the dataset is counted: a group of a million
    zero-length elements (8 MB) is refused from its bytes, within bounded memory, and a file whose
    group holds a few private elements beside the standard ones is still read."""
    import struct

    from service.io import dicom_structure

    valid = corpus.dicom(np.zeros((2, 8, 8)))
    head = 128 + 4
    group_end = head + 12 + struct.unpack("<I", valid[head + 8:head + 12])[0]
    extra = lambda n: b"".join(struct.pack("<HH2sH", 2, 0x100 + k % 0xFE00, b"LO", 0) for k in range(n))  # noqa: E731
    assert read(tmp_path, valid[:group_end] + extra(20) + valid[group_end:], "few.dcm").array.shape[:2] == (8, 8)
    bomb = valid[:group_end] + extra(1) * 1_000_000 + valid[group_end:]
    tracemalloc.start()
    with pytest.raises(PayloadTooLarge, match=f"bomb.dcm: a DICOM file-meta group of more than "
                                              f"{dicom_structure.MAX_META_ELEMENTS} elements"):
        read(tmp_path, bomb, "bomb.dcm", limit_mb=64)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 4 * MB, peak


def _implicit_meta(valid: bytes, elements: bytes) -> bytes:
    """``valid`` (a DICOM file) with its file-meta group written in implicit VR (as some writers do,
    and pydicom reads), ``elements`` after the standard ones."""
    import io
    import struct

    from pydicom.filereader import _read_file_meta_info

    head = 128 + 4
    group_end = head + 12 + struct.unpack("<I", valid[head + 8:head + 12])[0]
    body = b""
    for el in _read_file_meta_info(io.BytesIO(valid[head:])):
        if el.tag != 0x00020000:
            v = el.value if isinstance(el.value, bytes) else str(el.value).encode()
            v += b"\0" * (len(v) % 2)
            body += struct.pack("<HHI", 2, el.tag & 0xFFFF, len(v)) + v
    body += elements
    return valid[:head] + struct.pack("<HHI", 2, 0, 4) + struct.pack("<I", len(body)) + body + valid[group_end:]


def test_a_file_meta_group_is_counted_as_pydicom_reads_it_in_implicit_vr_and_refused_past_an_undefined_length(
        tmp_path: Path) -> None:
    """Elements of a file-meta group written in implicit VR (pydicom reads an element whose VR is no
    two capitals so) are counted too: a few are read, a hundred thousand of ten bytes refused from
    their bytes; an element of undefined length (pydicom reads on past it) is a 415 naming the file."""
    import struct

    valid = corpus.dicom(np.zeros((2, 8, 8)))
    extra = lambda n: b"".join(struct.pack("<HHI", 2, 0x100 + k % 0xFE00, 2) + b"AB" for k in range(n))  # noqa: E731
    assert read(tmp_path, _implicit_meta(valid, extra(20)), "few.dcm").array.shape[:2] == (8, 8)
    bomb = _implicit_meta(valid, extra(100_000))
    tracemalloc.start()
    with pytest.raises(PayloadTooLarge, match="bomb.dcm: a DICOM file-meta group of more than"):
        read(tmp_path, bomb, "bomb.dcm", limit_mb=64)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 4 * MB, peak
    head = 128 + 4
    group_end = head + 12 + struct.unpack("<I", valid[head + 8:head + 12])[0]
    undefined = struct.pack("<HH2sHI", 2, 0x100, b"OB", 0, 0xFFFFFFFF) + b"XXXX" + struct.pack("<HHI", 0xFFFE, 0xE0DD, 0)
    with pytest.raises(UnsupportedFile, match=r"past.dcm: a DICOM file-meta element \(0002,0100\) of undefined length"):
        read(tmp_path, valid[:group_end] + undefined + valid[group_end:], "past.dcm")


def test_elements_pydicom_reads_as_implicit_vr_in_an_explicit_vr_dataset_are_counted(tmp_path: Path) -> None:
    """pydicom reads an element whose VR bytes are no two capitals as implicit VR (tag, 4-byte
    length): the count reads them so, and a dataset of more than MAX_ELEMENTS of them is refused
    (each value the bytes of an item tag, which sent a walk reading a 2-byte length out of step)."""
    import struct

    from service.io import dicom_structure

    valid = corpus.dicom(np.zeros((2, 8, 8)))
    n = dicom_structure.MAX_ELEMENTS + 1
    implicit = b"".join(struct.pack("<HHI", 0x7FE1, 0x1000 + k % 0xEF00, 4) + b"\xfe\xff\x00\x00" for k in range(n))
    assert read(tmp_path, valid + implicit[:12 * 20], "few.dcm").array.shape[:2] == (8, 8)
    with pytest.raises(PayloadTooLarge, match="many.dcm: a DICOM dataset of more than"):
        read(tmp_path, valid + implicit, "many.dcm", limit_mb=64)


def test_elements_behind_an_undefined_length_value_are_counted(tmp_path: Path) -> None:
    """pydicom takes the value of an element of undefined length that is no sequence (a private OB,
    encapsulated pixel data) up to the next sequence delimiter, whatever it holds, and reads on: the
    elements after it are counted, and a dataset of more than MAX_ELEMENTS of them is refused (the
    count stopped at the first byte that was no fragment item, and pydicom read them all)."""
    import struct

    from service.io import dicom_structure

    valid = corpus.dicom(np.zeros((2, 8, 8)))
    hidden = struct.pack("<HH2sHI", 0x7FE1, 0x0010, b"OB", 0, 0xFFFFFFFF) + b"not an item" + \
        struct.pack("<HHI", 0xFFFE, 0xE0DD, 0)
    tiny = b"".join(struct.pack("<HH2sH", 0x7FE3 + 2 * (k // 60000), k % 60000 + 1, b"LO", 0)
                    for k in range(dicom_structure.MAX_ELEMENTS + 1))
    assert read(tmp_path, valid + hidden + tiny[:8 * 20], "few.dcm").array.shape[:2] == (8, 8)
    tracemalloc.start()
    with pytest.raises(PayloadTooLarge, match="many.dcm: a DICOM dataset of more than"):
        read(tmp_path, valid + hidden + tiny, "many.dcm", limit_mb=64)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 64 * MB, peak


def test_a_deflated_dicom_within_the_limit_is_read(tmp_path: Path) -> None:
    pixels = np.arange(3 * 8 * 6, dtype=np.uint16).reshape(3, 8, 6)
    vol = read(tmp_path, corpus.dicom(pixels, ts=uid.DeflatedExplicitVRLittleEndian), "ok.dcm")
    np.testing.assert_array_equal(vol.array, pixels.transpose(2, 1, 0))


def test_a_multiframe_header_declaring_more_than_the_limit_is_413_before_decoding(tmp_path: Path) -> None:
    ds_bytes = corpus.dicom(np.zeros((2, 64, 64), np.uint16))
    big = ds_bytes.replace(b"IS\x02\x002 ", b"IS\x06\x0099999 ")   # NumberOfFrames 2 -> 99999
    assert big != ds_bytes
    with pytest.raises(PayloadTooLarge, match="frames.dcm"):
        read(tmp_path, big, "frames.dcm")


@pytest.mark.parametrize(("frame", "ts"), [(corpus.jpeg_claiming(20000, 20000), uid.JPEGBaseline8Bit),
                                           (corpus.jpeg_claiming(20000, 20000), uid.JPEGLSLossless),
                                           (corpus.rle_bomb(), uid.RLELossless)])
def test_compressed_frames_larger_than_their_header_are_refused_before_decoding(tmp_path: Path, frame: bytes,
                                                                                ts: str) -> None:
    with pytest.raises(UnsupportedFile, match="frame 0 does not match"):
        read(tmp_path, corpus.encapsulated([frame], 8, 8, ts), "lying.dcm")


def test_a_bomb_inside_a_zip_is_stopped_and_named(tmp_path: Path) -> None:
    data = corpus.zipped({"series/IM0001": corpus.deflate_bomb(64)})
    with pytest.raises(PayloadTooLarge) as info:
        read(tmp_path, data, "study.zip", limit_mb=4)
    assert "study.zip: member 1 of 1" in info.value.detail and "IM0001" not in info.value.detail


@pytest.mark.parametrize("inner", ["zip", "gzip"])
def test_archives_nested_in_a_zip_are_refused_by_name(tmp_path: Path, inner: str) -> None:
    member = (corpus.zipped({"a.dcm": corpus.dicom(np.ones((4, 4), np.uint16))}) if inner == "zip"
              else corpus.gzip_bomb(1))
    with pytest.raises(UnsupportedFile) as info:
        read(tmp_path, corpus.zipped({"inner.bin": member}), "outer.zip")
    assert "outer.zip: member 1 of 1" in info.value.detail and "nested" in info.value.detail


def test_a_zip_member_inflating_past_the_limit_is_stopped(tmp_path: Path) -> None:
    data = corpus.zipped({"a.dcm": b"\0" * (6 * MB)})
    with pytest.raises(PayloadTooLarge, match="big.zip"):
        read(tmp_path, data, "big.zip", limit_mb=4)


def test_a_gzip_whose_header_declares_too_much_is_413(tmp_path: Path) -> None:
    with pytest.raises(PayloadTooLarge, match="bomb.nii.gz"):
        read(tmp_path, corpus.gzip_bomb(16), "bomb.nii.gz", limit_mb=4)


def test_the_decoded_total_of_one_request_is_bounded(tmp_path: Path) -> None:
    """Each file alone is within its limit; together they pass the request's."""
    budget = DecodeBudget(6 * MB, 10 * MB)
    path = tmp_path / "g.nii.gz"
    path.write_bytes(corpus.gzip_bomb(2))
    read_upload(path, "a.nii.gz", budget=budget.file("a.nii.gz"))
    read_upload(path, "b.nii.gz", budget=budget.file("b.nii.gz"))
    with pytest.raises(PayloadTooLarge, match="c.nii.gz: the files of this request decode to more than"):
        read_upload(path, "c.nii.gz", budget=budget.file("c.nii.gz"))


def test_a_zipped_series_of_deflated_files_is_read_in_order(tmp_path: Path) -> None:
    """GDCM gets deflated members already inflated (by the bounded reader) and orders the series."""
    rng = np.random.default_rng(4)
    planes = [(rng.random((8, 6)) * 1000).astype(np.uint16) for _ in range(3)]
    members = {f"IM{k:04d}": corpus.dicom(p, k, uid.DeflatedExplicitVRLittleEndian) for k, p in enumerate(planes)}
    vol = read(tmp_path, corpus.zipped(dict(reversed(list(members.items())))), "deflated.zip")
    np.testing.assert_array_equal(vol.array, np.stack(planes).transpose(2, 1, 0))
    np.testing.assert_allclose(vol.spacing, [1, 1, 3])
    multiframe = corpus.dicom(np.stack(planes), 0, uid.DeflatedExplicitVRLittleEndian)
    single = read(tmp_path, corpus.zipped({"IM0000": multiframe}), "one.zip")
    np.testing.assert_array_equal(single.array, np.stack(planes).transpose(2, 1, 0))


def test_a_zipped_series_is_held_to_one_files_voxel_limit_together(tmp_path: Path) -> None:
    """Each image of a ZIP within the per-file limit, the series they make over it (a few KB of
    constant images would otherwise become a volume of any size): 413 before GDCM builds it."""
    plane = np.full((256, 256), 7, np.uint16)                          # 0.25 MB as float32
    members = {f"IM{k:04d}": corpus.dicom(plane, k) for k in range(6)}
    declared = r"series\.zip: its images declare 327,680 voxels \(1\.25 MB as float32\), more than the 1 MB"
    with pytest.raises(PayloadTooLarge, match=declared):
        read(tmp_path, corpus.zipped(members), "series.zip", limit_mb=1, request_mb=64)
    assert read(tmp_path, corpus.zipped(dict(list(members.items())[:3])), "three.zip", limit_mb=1,
                request_mb=64).array.shape[2] == 3
    frames = corpus.dicom(np.full((3, 256, 200), 7, np.uint16))      # 0.59 MB: one image, zipped, charged once
    assert read(tmp_path, corpus.zipped({"IM0": frames}), "one.zip", limit_mb=1, request_mb=64).array.shape[2] == 3


def test_a_zip_declaring_too_many_members_is_refused_before_its_list_is_parsed(tmp_path: Path,
                                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """The member count (and the list's size) come from the end record: the list itself is never read."""
    import service.io.archive as archive

    path = tmp_path / "many.zip"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        for i in range(archive.MAX_MEMBERS + 1):
            z.writestr(f"{i}", b"")
    parsed: list[int] = []
    monkeypatch.setattr(archive.zipfile, "ZipFile", lambda *a, **k: parsed.append(1))
    with pytest.raises(UnusableImage, match=r"many.zip: too many files in the archive \(5001 members"):
        read_upload(path, "many.zip")
    assert not parsed


def _listing(names: list[bytes], declared: int) -> bytes:
    """A ZIP of one empty stored member and a member list of an entry per name, every entry pointing at
    that member, its end record declaring ``declared`` members."""
    import struct

    local = struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, 0, 0, 0, 0, 0, 0, 1, 0) + b"a"
    listing = b"".join(struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, 0, 0, 0, 0, 0, 0, len(name),
                                   0, 0, 0, 0, 0, 0) + name for name in names)
    return local + listing + struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, declared, declared, len(listing), len(local), 0)


def test_a_zip_whose_end_record_understates_its_members_is_refused_before_its_list_is_parsed(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An end record that declares one member in front of a list of 5,001 (47 bytes each, well under
    the list's byte limit) is not believed: the entries are counted before the ZIP reader builds them."""
    import service.io.archive as archive

    path = tmp_path / "lying.zip"
    path.write_bytes(_listing([b"%d" % (i % 10) for i in range(archive.MAX_MEMBERS + 1)], declared=1))
    parsed: list[int] = []
    monkeypatch.setattr(archive.zipfile, "ZipFile", lambda *a, **k: parsed.append(1))
    with pytest.raises(UnusableImage, match=r"lying.zip: too many files in the archive \(more than 5000 members"):
        read_upload(path, "lying.zip")
    assert not parsed


def test_a_zip_member_without_a_name_is_no_file(tmp_path: Path) -> None:
    """A nameless entry (which the ZIP reader cannot ask whether it is a folder) is left out like a
    folder: the archive then holds no series."""
    path = tmp_path / "nameless.zip"
    path.write_bytes(_listing([b""], declared=1))
    with pytest.raises(UnsupportedFile, match="nameless.zip: the ZIP archive holds no DICOM series"):
        read_upload(path, "nameless.zip")


def test_rle_frames_padded_to_an_even_length_are_read(tmp_path: Path) -> None:
    """PS3.5 Annex G pads each RLE segment of odd length with one byte: the guard counts a segment
    decoded whole and stops there (it counted the pad as a run's header and refused half a real
    scanner's RLE slices as larger than their header). Files as pydicom's encoder writes them, some
    of their segments padded, read back exactly; a segment with more than its pad left is refused."""
    import io

    from pydicom import dcmread
    from pydicom.encaps import generate_frames

    padded = 0
    for seed in range(6):
        px = (np.random.default_rng(seed).random((2, 9, 7)) * 300).astype(np.uint16)
        px[:, -1, -1] = 0                                    # air: the values are read as they are
        ds = dcmread(io.BytesIO(corpus.dicom(px)))
        ds.compress(uid.RLELossless)
        out = io.BytesIO()
        ds.save_as(out)
        for frame in generate_frames(ds.PixelData, number_of_frames=2):
            padded += _decoded_before_the_end(frame)
        vol = read(tmp_path, out.getvalue(), f"rle{seed}.dcm")
        np.testing.assert_array_equal(vol.array, px.transpose(2, 1, 0))
    assert padded > 0                                       # the case the guard got wrong was among them
    with pytest.raises(UnsupportedFile, match="frame 0 does not match"):
        read(tmp_path, corpus.encapsulated([corpus.rle_bomb()], 8, 8, uid.RLELossless), "lying.dcm")


def test_an_rle_segment_longer_than_any_encoding_of_its_pixels_is_refused_unread() -> None:
    """A segment of RLE's no-op bytes (128) decodes to nothing however long it is: one twice as long as
    its pixels' bytes is refused before it is stepped through (30 MB of them, 60 KB zipped, took
    12.6 s of CPU to refuse); a real encoder's longest segment (every byte its own literal run) fits."""
    from service.io.dicom_guard import _rle_fits

    header = (1).to_bytes(4, "little") + (64).to_bytes(4, "little") + bytes(56)
    assert not _rle_fits(header + bytes([128]) * (2 * 64 + 3), 64, 1)
    assert _rle_fits(header + bytes([0, 7]) * 64, 64, 1)                # 64 literal runs of one byte
    assert not _rle_fits(header + bytes([0, 7]) * 65, 64, 1)            # one byte too many decoded


def _decoded_before_the_end(frame: bytes) -> int:
    """How many of ``frame``'s RLE segments hold their pixels' bytes before their last byte (padded)."""
    n = int.from_bytes(frame[:4], "little")
    offsets = [int.from_bytes(frame[4 + 4 * i:8 + 4 * i], "little") for i in range(n)] + [len(frame)]
    count = 0
    for start, end in zip(offsets, offsets[1:]):
        seg, pos, out = frame[start:end], 0, 0
        while pos < len(seg) and out < 9 * 7:
            h = seg[pos]
            out, pos = (out + 257 - h, pos + 2) if h > 128 else (out + h + 1, pos + h + 2) if h < 128 else (out, pos + 1)
        count += pos < len(seg)
    return count


def test_a_monochrome1_dicom_is_refused_naming_its_photometric_interpretation(tmp_path: Path) -> None:
    """MONOCHROME1 stores signal dark: read as it is, a brain would be the darkest tissue and the
    localiser would find none (a 200 with every slice empty). It is refused, saying what to send."""
    import io

    from pydicom import dcmread

    ds = dcmread(io.BytesIO(corpus.dicom(np.zeros((2, 8, 8), np.uint16))))
    ds.PhotometricInterpretation = "MONOCHROME1"
    out = io.BytesIO()
    ds.save_as(out)
    with pytest.raises(UnusableImage, match="mono.dcm: DICOM pixel data of PhotometricInterpretation MONOCHROME1; .*"
                                            "export the series as MONOCHROME2"):
        read(tmp_path, out.getvalue(), "mono.dcm")
    with pytest.raises(UnusableImage, match="mono.zip: member 1 of 1: DICOM pixel data of PhotometricInterpretation "
                                            "MONOCHROME1"):            # not "unreadable" (415) in a ZIP
        read(tmp_path, corpus.zipped({"IM0001": out.getvalue()}), "mono.zip")


def test_a_multi_frame_file_whose_compression_has_no_decoder_here_says_so(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """pydicom without a plugin for the transfer syntax raises RuntimeError: a 415 naming the syntax
    and what to send, not "corrupt, truncated or inconsistent"."""
    from service.io import dicom

    real = dicom.load_dataset

    class NoPlugin:
        def __init__(self, ds: object) -> None:
            self.file_meta = ds.file_meta
            self.file_meta.TransferSyntaxUID = uid.JPEGLosslessSV1

        @property
        def pixel_array(self) -> None:
            raise RuntimeError("all plugins are missing dependencies")

    monkeypatch.setattr(dicom, "load_dataset", lambda *a, **k: NoPlugin(real(*a, **k)))
    with pytest.raises(UnsupportedFile, match="enh.dcm: DICOM pixel data compressed as JPEG Lossless.*single-frame"):
        read(tmp_path, corpus.dicom(np.zeros((2, 8, 8), np.uint16)), "enh.dcm")
