"""DICOM files read with every decoder bounded before or while it decodes.

* Deflated Explicit VR Little Endian: the dataset is inflated here, in chunks, charged to the file's
  :class:`~service.io.limits.FileBudget` as it grows (pydicom would inflate it whole, unbounded).
* The dataset's elements and items, at every depth, and its header's bytes are counted from its raw
  bytes before pydicom builds any of them (:func:`~service.io.dicom_structure.check_structure`), the
  file-meta group's before pydicom reads it (:func:`~service.io.dicom_structure.check_file_meta`).
* Pixel data: ``Rows x Columns x NumberOfFrames x SamplesPerPixel`` is charged before any pixel is
  decoded (multi-frame included); colour pixel data (``SamplesPerPixel`` above 1) are refused (422).
* Encapsulated pixel data: every frame is checked against ``Rows``/``Columns`` before a codec sees it:
  JPEG / JPEG-LS frames by their SOF marker, JPEG 2000 by its SIZ marker, RLE by counting (not
  producing) what each segment would decode to. Other encapsulated syntaxes (video, ...) are refused.

Messages name the client's file (``filename``, which for a ZIP member includes the member's name).
"""

from __future__ import annotations

import zlib
from pathlib import Path
from typing import BinaryIO

import pydicom
from pydicom import uid
from pydicom.dataset import Dataset, FileDataset
from pydicom.encaps import generate_frames
from pydicom.filebase import DicomBytesIO
from pydicom.filereader import _read_file_meta_info, read_dataset, read_preamble

from service.core.errors import UnsupportedFile, UnusableImage
from service.io.dicom_structure import check_file_meta, check_structure
from service.io.limits import FileBudget

JPEG_FAMILY = set(uid.JPEGTransferSyntaxes) | set(uid.JPEGLSTransferSyntaxes)
J2K_FAMILY = set(uid.JPEG2000TransferSyntaxes) | {uid.HTJ2K, uid.HTJ2KLossless, uid.HTJ2KLosslessRPCL}
SOF_MARKERS = {m for m in range(0xC0, 0xD0) if m not in (0xC4, 0xC8, 0xCC)} | {0xF7}
CHUNK = 1 << 20


def load_dataset(path: Path, filename: str, budget: FileBudget, require_pixels: bool = True) -> Dataset:
    """The dataset of one DICOM file, its pixel data checked against ``budget`` (not yet decoded);
    without ``require_pixels`` a dataset without pixel data is returned as it is.

    Raises:
        UnsupportedFile: not DICOM, no pixel data, or pixel data that do not match the header.
        PayloadTooLarge: the dataset or its pixels decode to more than the budget allows.
    """
    with open(path, "rb") as fp:
        preamble = read_preamble(fp, False)
        check_file_meta(fp, filename)
        meta = _read_file_meta_info(fp)
        if meta.get("TransferSyntaxUID") == uid.DeflatedExplicitVRLittleEndian:
            raw = _inflate(fp, budget)
            check_structure(DicomBytesIO(raw), filename, False, True)
            meta.TransferSyntaxUID = uid.ExplicitVRLittleEndian
            ds = FileDataset(filename, read_dataset(DicomBytesIO(raw), False, True), preamble=preamble,
                             file_meta=meta, is_implicit_VR=False, is_little_endian=True)
        else:
            syntax = uid.UID(meta.get("TransferSyntaxUID", uid.ImplicitVRLittleEndian))
            check_structure(fp, filename, syntax == uid.ImplicitVRLittleEndian, syntax != uid.ExplicitVRBigEndian)
            fp.seek(0)
            ds = pydicom.dcmread(fp)
    if require_pixels or "PixelData" in ds:
        check_pixels(ds, filename, budget)
    return ds


def _inflate(fp: BinaryIO, budget: FileBudget) -> bytes:
    """The raw-deflate stream from ``fp`` decoded in bounded steps, each charged before it is kept."""
    d = zlib.decompressobj(-zlib.MAX_WBITS)
    out = bytearray()
    while not d.eof and (data := fp.read(CHUNK)):
        while data and not d.eof:
            part = d.decompress(data, CHUNK)
            budget.inflate(len(part))
            out += part
            data = d.unconsumed_tail
    return bytes(out)


PHOTOMETRIC_TERMS = frozenset({"MONOCHROME1", "MONOCHROME2", "PALETTE COLOR", "RGB", "HSV", "ARGB", "CMYK", "YBR_FULL",
                               "YBR_FULL_422", "YBR_PARTIAL_422", "YBR_PARTIAL_420", "YBR_ICT", "YBR_RCT"})
"""The defined terms of PhotometricInterpretation (PS3.3 C.7.6.3.1.2): the only values an answer names
(a tag's free text could hold anything, a name among it)."""


def check_pixels(ds: Dataset, filename: str, budget: FileBudget) -> None:
    """Charge the declared pixel array and check compressed frames against it, before decoding."""
    if "PixelData" not in ds:
        raise UnsupportedFile(f"{filename}: a DICOM file without pixel data")
    try:
        rows, cols = int(ds.Rows), int(ds.Columns)
        frames = int(getattr(ds, "NumberOfFrames", 1) or 1)
        spp = int(getattr(ds, "SamplesPerPixel", 1) or 1)
    except (AttributeError, TypeError, ValueError) as exc:
        raise UnsupportedFile(f"{filename}: DICOM pixel data without a valid size (Rows, Columns, frames)") from exc
    if min(rows, cols, frames, spp) < 1:
        raise UnsupportedFile(f"{filename}: DICOM pixel data of size {rows} x {cols} x {frames}")
    budget.slices(frames, "frames")              # before a loop over them, or their decoding
    photometric = str(getattr(ds, "PhotometricInterpretation", "MONOCHROME2") or "MONOCHROME2").strip().upper()
    if spp == 1 and photometric != "MONOCHROME2":   # a palette's indices are no grey values; MONOCHROME1 runs the other way
        named = photometric if photometric in PHOTOMETRIC_TERMS else "other than MONOCHROME2"  # never a free text
        raise UnusableImage(f"{filename}: DICOM pixel data of PhotometricInterpretation {named}; grey "
                            "values with signal bright (MONOCHROME2) are required: export the series as MONOCHROME2")
    if spp != 1:                        # colour: its channels would be taken for slices or frames
        raise UnusableImage(f"{filename}: DICOM pixel data with {spp} samples per pixel (colour); one grey value "
                            "per pixel is required")
    budget.voxels(rows * cols * frames * spp)
    ts = ds.file_meta.get("TransferSyntaxUID") if hasattr(ds, "file_meta") else None
    if ts is None or not uid.UID(ts).is_encapsulated:
        bits = int(getattr(ds, "BitsAllocated", 16) or 16)
        declared = (rows * cols * frames * spp * bits + 7) // 8
        if len(ds.PixelData) < declared:
            raise UnsupportedFile(f"{filename}: DICOM pixel data shorter than its header declares (truncated file)")
        if len(ds.PixelData) - declared >= max(rows * cols * spp * bits // 8, 2):   # a frame more: decoded as one
            raise UnsupportedFile(f"{filename}: DICOM pixel data longer than its header declares ({len(ds.PixelData)} "
                                  f"bytes for {frames} frame(s) of {rows} x {cols})")
        return
    if ts == uid.RLELossless:
        bits = int(getattr(ds, "BitsAllocated", 8) or 8)
        check = lambda f: _rle_fits(f, rows * cols, spp * ((bits + 7) // 8))  # noqa: E731
    elif ts in JPEG_FAMILY:
        check = lambda f: _jpeg_size(f) == (cols, rows)  # noqa: E731
    elif ts in J2K_FAMILY:
        check = lambda f: _j2k_size(f) == (cols, rows)  # noqa: E731
    else:
        raise UnsupportedFile(f"{filename}: DICOM pixel data compressed with an unsupported transfer syntax")
    for i, frame in enumerate(generate_frames(ds.PixelData, number_of_frames=frames)):
        if i >= frames or not check(frame):
            raise UnsupportedFile(f"{filename}: compressed DICOM frame {i} does not match its header "
                                  f"({rows} x {cols})")


def _rle_fits(frame: bytes, segment_bytes: int, max_segments: int) -> bool:
    """Whether every RLE segment of ``frame`` decodes to at most ``segment_bytes`` (counted, not decoded;
    a segment that has decoded whole may end in the one pad byte of PS3.5 Annex G, nothing more). A
    segment longer than twice ``segment_bytes`` is refused before it is read: no encoder writes one,
    and its no-op bytes (128) would otherwise be stepped over one by one, a Python loop over all of
    a file's bytes.

    Example (one segment of 4 bytes: a literal run of 3, then a repeat of 1, padded to even length):
        >>> header = (1).to_bytes(4, "little") + (64).to_bytes(4, "little") + bytes(56)
        >>> _rle_fits(header + bytes([2, 7, 8, 9, 0, 5, 0]), 4, 1), _rle_fits(header + bytes([2, 7, 8, 9, 1, 5, 5]), 4, 1)
        (True, False)
    """
    if len(frame) < 64:
        return False
    n = int.from_bytes(frame[:4], "little")
    if not 1 <= n <= min(15, max_segments):
        return False
    offsets = [int.from_bytes(frame[4 + 4 * i:8 + 4 * i], "little") for i in range(n)] + [len(frame)]
    for start, end in zip(offsets, offsets[1:]):
        if not 64 <= start <= end <= len(frame) or end - start > 2 * segment_bytes + 2:
            return False            # longer than any encoding of it (each byte its own literal run) is
        seg, pos, out = frame[start:end], 0, 0
        while pos < len(seg):
            if out == segment_bytes:        # decoded whole: one byte more pads the segment to an even length
                if len(seg) - pos > 1:
                    return False
                break
            h = seg[pos]
            if h > 128:
                out, pos = out + 257 - h, pos + 2
            elif h < 128:
                out, pos = out + h + 1, pos + h + 2
            else:
                pos += 1
            if out > segment_bytes:
                return False
    return True


def _jpeg_size(frame: bytes) -> tuple[int, int] | None:
    """(width, height) from the SOF (or JPEG-LS SOF55) marker of a JPEG frame."""
    if frame[:2] != b"\xff\xd8":
        return None
    pos = 2
    while pos + 9 <= len(frame):
        if frame[pos] != 0xFF:
            return None
        marker = frame[pos + 1]
        if marker == 0xFF:
            pos += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:
            pos += 2
            continue
        if marker in SOF_MARKERS:
            return int.from_bytes(frame[pos + 7:pos + 9], "big"), int.from_bytes(frame[pos + 5:pos + 7], "big")
        pos += 2 + int.from_bytes(frame[pos + 2:pos + 4], "big")
    return None


def _j2k_size(frame: bytes) -> tuple[int, int] | None:
    """(width, height) from the SIZ marker of a JPEG 2000 codestream (bare or in a JP2 box)."""
    at = frame.find(b"\xff\x4f\xff\x51", 0, 4096)
    if at < 0 or len(frame) < at + 24:
        return None
    x, y, x0, y0 = (int.from_bytes(frame[at + 8 + 4 * i:at + 12 + 4 * i], "big") for i in range(4))
    return x - x0, y - y0


__all__ = ["check_pixels", "load_dataset"]
