"""Text headers of NRRD and MetaImage uploads, rewritten so that a reader can only see the upload's bytes.

NRRD and MetaImage headers may name another file that holds the voxel data (``data file:`` in NRRD,
``ElementDataFile = <path>`` in MetaImage). A client's header must never make the server open one of
its own files, so an upload is never handed to a reader as sent:

* the whole header is parsed, however long (up to :data:`MAX_HEADER_BYTES`; a longer one is refused);
* a header that names another file anywhere -- whatever the spelling, case or position of the field,
  existing path or not -- is refused with the same 415, so the answer tells nothing about the server;
* the header's lines end where its reader ends them (NRRD's at a bare ``\\r`` too), so no field can
  hide behind a line end one reader sees and the other does not;
* the reader gets a *new* header written here from an allow-list of geometry and encoding fields,
  followed by the upload's own data bytes: fields that could name a file are never copied. A
  compressed MetaImage's data are inflated here, bounded, and must give the size the header declares
  (ITK's reader would leave the voxels of a stream that fails to inflate as its memory held them);
* the header's shape is checked here, in Python integers, before any reader sees it
  (:func:`declared_grid`): 1-4 axes of 1 to 2**31 - 1 voxels, a value type and encoding the reader
  knows; a MetaImage's yes/no fields are written ``True`` or ``False`` as MetaIO reads them (a value
  starting with T, t or 1 is yes), so that ``CompressedData = 1`` is inflated here, bounded, like
  ``True``. ITK's NRRD reader crashes on a ``dimension`` of 12, its
  MetaImage reader loops for ever on an ``NDims`` of -1, both count sizes of 2**32 and more in 32 bits
  (a declared size wraps to a small voxel count while the reader allocates the full one), and a gzip NRRD's
  ``byte skip`` is inflated and thrown away uncounted.

Example:
    >>> import io
    >>> src = io.BytesIO(b"NRRD0004\\n# note\\ntype: uchar\\ndimension: 1\\nsizes: 2\\nspacings: 1.5\\n\\n\\x01\\x02")
    >>> dst = io.BytesIO(); _ = clean_header(src, dst, "nrrd", "a.nrrd")
    >>> dst.getvalue()
    b'NRRD0004\\ntype: uchar\\ndimension: 1\\nsizes: 2\\nspacings: 1.5\\n\\n\\x01\\x02'
"""

from __future__ import annotations

import re
import shutil
import zlib
from typing import BinaryIO

import numpy as np

from service.core.errors import PayloadTooLarge, UnsupportedFile

MAX_HEADER_BYTES = 1 << 20

NRRD_FIELDS = {
    "type", "dimension", "sizes", "endian", "encoding", "space", "spacedimension", "spacedirections", "spaceorigin",
    "kinds", "spacings", "thicknesses", "axismins", "axismaxs", "centers", "centerings", "spaceunits", "units",
    "measurementframe", "lineskip", "byteskip", "oldmin", "oldmax", "min", "max", "blocksize",
}
MHA_FIELDS = {
    "objecttype", "ndims", "dimsize", "elementtype", "elementspacing", "elementsize", "offset", "position", "origin",
    "transformmatrix", "rotation", "orientation", "centerofrotation", "anatomicalorientation", "binarydata",
    "binarydatabyteordermsb", "elementbyteordermsb", "compresseddata", "compresseddatasize",
    "elementnumberofchannels", "headersize",
}
MHA_CANONICAL = {k.lower(): k for k in (
    "ObjectType", "NDims", "DimSize", "ElementType", "ElementSpacing", "ElementSize", "Offset", "Position", "Origin",
    "TransformMatrix", "Rotation", "Orientation", "CenterOfRotation", "AnatomicalOrientation", "BinaryData",
    "BinaryDataByteOrderMSB", "ElementByteOrderMSB", "CompressedData", "CompressedDataSize",
    "ElementNumberOfChannels", "HeaderSize")}
_DETACHED = re.compile(rb"data\s*file|element\s*data\s*file", re.I)


def _key(raw: bytes) -> str:
    """A field name for comparison: lower case, no white space."""
    return re.sub(r"\s+", "", raw.decode("latin-1")).lower()


def _detached(filename: str, kind: str) -> UnsupportedFile:
    return UnsupportedFile(f"{filename}: a {kind.upper()} header that refers to another file (detached data); "
                           "upload one file with its voxel data attached")


_NRRD_LINE_END = re.compile(rb"\r\n|\n|\r")   # teem ends a line at a bare \r too
_MHA_LINE_END = re.compile(rb"\n")             # MetaIO at \n only (a \r stays in the value)


def _lines(head: bytes, kind: str) -> list[tuple[bytes, int]]:
    """Each line of ``head`` (without its end) and the offset just after it, ending lines where the
    ``kind``'s reader ends them: a field after a bare ``\\r`` is a field to NRRD's reader.

    Example:
        >>> _lines(b"a\\rb\\r\\nc", "nrrd"), _lines(b"a\\rb\\r\\nc", "mha")
        ([(b'a', 2), (b'b', 5), (b'c', 6)], [(b'a\\rb', 5), (b'c', 6)])
    """
    ends = _NRRD_LINE_END if kind == "nrrd" else _MHA_LINE_END
    out, pos = [], 0
    while pos < len(head):
        end = ends.search(head, pos)
        line_end, nxt = (len(head), len(head)) if end is None else (end.start(), end.end())
        out.append((head[pos:line_end].rstrip(b"\r"), nxt))
        pos = nxt
    return out


def header_fields(header: bytes, kind: str) -> dict[str, bytes]:
    """The fields of a header rebuilt here, by :func:`_key` name (NRRD's magic line left out).

    Example:
        >>> header_fields(b"ObjectType = Image\\nElementType = MET_UCHAR\\n", "mha")["elementtype"]
        b' MET_UCHAR'
    """
    fields: dict[str, bytes] = {}
    for line in header.split(b"\n")[1 if kind == "nrrd" else 0:]:
        key, sep, value = line.partition(b":" if kind == "nrrd" else b"=")
        if sep:
            fields[_key(key)] = value
    return fields


MAX_AXES = 4
MAX_AXIS_VOXELS = 2**31 - 1
MAX_CHANNELS = 16
NRRD_ITEM_BYTES = {
    **dict.fromkeys(("signed char", "int8", "int8_t", "uchar", "unsigned char", "uint8", "uint8_t"), 1),
    **dict.fromkeys(("short", "short int", "signed short", "signed short int", "int16", "int16_t", "ushort",
                     "unsigned short", "unsigned short int", "uint16", "uint16_t"), 2),
    **dict.fromkeys(("int", "signed int", "int32", "int32_t", "uint", "unsigned int", "uint32", "uint32_t", "float"), 4),
    **dict.fromkeys(("longlong", "long long", "long long int", "signed long long", "signed long long int", "int64",
                     "int64_t", "ulonglong", "unsigned long long", "unsigned long long int", "uint64", "uint64_t",
                     "double"), 8)}
"""Bytes of one value by NRRD ``type`` (teem's spellings, white space collapsed, lower case)."""
NRRD_ENCODINGS = {"raw": False, "txt": False, "text": False, "ascii": False, "hex": False, "gz": True, "gzip": True}
"""The NRRD encodings read, and whether each is compressed (bzip2 is not in ITK's build)."""
MHA_YES_NO = ("binarydata", "binarydatabyteordermsb", "elementbyteordermsb", "compresseddata")


def declared_grid(header: bytes, kind: str, filename: str) -> tuple[list[int], int]:
    """The axes' sizes and the values per voxel a rebuilt header declares; :class:`UnsupportedFile`
    naming the field for a header its reader would misread, crash or hang on (see the module).

    Example:
        >>> declared_grid(b"NRRD0004\\ntype: short\\ndimension: 3\\nsizes: 4 5 6\\nencoding: gzip\\n\\n", "nrrd", "a")
        ([4, 5, 6], 1)
        >>> declared_grid(b"NDims = -1\\nDimSize = 2\\nElementType = MET_UCHAR\\n", "mha", "b.mha")
        Traceback (most recent call last):
        ...
        service.core.errors.UnsupportedFile: b.mha: its MHA header's NDims is not a whole number of 1 to 4 axes
    """
    fields, name = header_fields(header, kind), kind.upper()

    def problem(what: str) -> UnsupportedFile:
        return UnsupportedFile(f"{filename}: its {name} header's {what}")

    def whole(field: str, label: str, low: int, high: int) -> int:
        text = fields.get(field, b"").strip()
        if not re.fullmatch(rb"\d+", text) or not low <= int(text) <= high:
            raise problem(f"{label} is not a whole number of {low} to {high} axes" if field in ("dimension", "ndims")
                          else f"{label} is not a whole number from {low} to {high}")
        return int(text)

    if kind == "nrrd":
        axes = whole("dimension", "dimension", 1, MAX_AXES)
        sizes_field, label = "sizes", "sizes"
        item = NRRD_ITEM_BYTES.get(re.sub(rb"\s+", b" ", fields.get("type", b"").strip()).decode("latin-1").lower())
        if item is None:
            raise problem("type is not a number type this reader knows")
        encoding = fields.get("encoding", b"raw").strip().decode("latin-1").lower()
        if encoding not in NRRD_ENCODINGS:
            raise problem(f"encoding {encoding[:20]!r} is not one this reader knows (raw, ascii, hex or gzip)")
        skip = fields.get("byteskip", b"0").strip()
        if NRRD_ENCODINGS[encoding] and skip not in (b"0", b""):
            raise problem("byte skip is not 0 for compressed data (the skipped bytes would be inflated unbounded)")
        channels = 1
    else:
        axes = whole("ndims", "NDims", 1, MAX_AXES)
        sizes_field, label = "dimsize", "DimSize"
        item = MET_ITEM_BYTES.get(fields.get("elementtype", b"").decode("latin-1").strip().upper())
        if item is None:
            raise problem("ElementType is not a number type this reader knows")
        channels = whole("elementnumberofchannels", "ElementNumberOfChannels", 1, MAX_CHANNELS) \
            if "elementnumberofchannels" in fields else 1
    sizes = fields.get(sizes_field, b"").split()
    if len(sizes) != axes or not all(re.fullmatch(rb"\d+", s) and 1 <= int(s) <= MAX_AXIS_VOXELS for s in sizes):
        raise problem(f"{label} does not give {axes} whole numbers from 1 to {MAX_AXIS_VOXELS}")
    return [int(s) for s in sizes], channels


def declared_values(header: bytes, kind: str, filename: str) -> int:
    """The number of voxel values a rebuilt header declares (channels included), counted in Python
    integers (:func:`declared_grid`'s checks).

    Example:
        >>> declared_values(b"NRRD0004\\ntype: short\\ndimension: 3\\nsizes: 4 5 6\\nencoding: gzip\\n\\n", "nrrd", "a")
        120
    """
    sizes, channels = declared_grid(header, kind, filename)
    return int(np.prod(sizes, dtype=object)) * channels


def clean_header(src: BinaryIO, dst: BinaryIO, kind: str, filename: str, max_inflated: int = 1 << 30) -> bytes:
    """Copy an NRRD (``kind="nrrd"``) or MetaImage (``"mha"``) upload from ``src`` to ``dst`` with a
    header rebuilt from allowed fields; its data bytes are copied unchanged, but for a compressed
    MetaImage, whose data are inflated here (to at most ``max_inflated`` bytes). Returns the rebuilt
    header (for :func:`~service.io.header_geometry.geometry_problem`, once the reader has read what it declares).

    Raises:
        UnsupportedFile: the header names another file, is longer than :data:`MAX_HEADER_BYTES`, or
            is incomplete (no data follow it); compressed MetaImage data that do not inflate to the
            size the header declares. The message names ``filename`` only.
    """
    head = src.read(MAX_HEADER_BYTES + 1)
    complete = len(head) <= MAX_HEADER_BYTES
    lines = _lines(head, kind)
    header, data_at = (_nrrd if kind == "nrrd" else _mha)(lines, filename)
    if data_at is None:
        # No end of header: the whole (allowed) prefix is header. Any reference to a file refuses it,
        # whether or not the header would be complete; otherwise it is too long or has no data.
        if any(_DETACHED.search(line.split(b":", 1)[0].split(b"=", 1)[0]) for line, _ in lines):
            raise _detached(filename, kind)
        if not complete:
            raise UnsupportedFile(f"{filename}: a {kind.upper()} header longer than {MAX_HEADER_BYTES >> 10} KB")
        raise UnsupportedFile(f"{filename}: a {kind.upper()} header with no voxel data after it")
    declared_values(header, kind, filename)                # before any reader sees it
    if kind == "mha" and header_fields(header, "mha").get("compresseddata", b"").strip().lower() == b"true":
        _inflated_mha(header, head[data_at:], src, dst, filename, max_inflated)
        return header
    dst.write(header)
    dst.write(head[data_at:])
    shutil.copyfileobj(src, dst, 1 << 20)
    return header


def _nrrd(lines: list[tuple[bytes, int]], filename: str) -> tuple[bytes, int | None]:
    """The rebuilt NRRD header and the offset of the data (None: no blank line ends the header)."""
    out = [lines[0][0]] if lines else [b""]
    for line, after in lines[1:]:
        if not line.strip():
            return b"\n".join(out) + b"\n\n", after
        if line.startswith(b"#"):
            continue
        if b":=" in line:               # key/value pairs: free text, not needed
            if _DETACHED.search(line.split(b":=", 1)[0]):
                raise _detached(filename, "nrrd")
            continue
        key, sep, value = line.partition(b":")
        name = _key(key)
        if name == "datafile" or _DETACHED.search(key):
            raise _detached(filename, "nrrd")
        if sep and name in NRRD_FIELDS:
            out.append(key.strip() + b": " + value.strip())
    return b"", None


_TEXT_BYTES = bytes(range(32, 127)) + b"\t\r"
"""The bytes a MetaImage header line is written in (printable ASCII, a tab; a carriage return is
judged on its own below)."""
_HIGH_BYTES = bytes(range(128, 256))
_FIELD_NAME = re.compile(rb"[ \t]*[A-Za-z][A-Za-z0-9_]*[ \t]*")
"""A MetaImage field's name: a field whose value holds other bytes (a name or a comment in Latin-1
or UTF-8, as ITK writes metadata) is a field still, dropped as every field the service does not read."""


def _mha(lines: list[tuple[bytes, int]], filename: str) -> tuple[bytes, int | None]:
    """The rebuilt MetaImage header (ending ``ElementDataFile = LOCAL``) and the offset of the data."""
    out = []
    for line, after in lines:
        key, sep, value = line.partition(b"=")
        name = _key(key)
        if name == "elementdatafile":    # always the last field: the data follow it in the same file
            if value.strip().upper() != b"LOCAL":
                raise _detached(filename, "mha")
            return b"\n".join(out + [b"ElementDataFile = LOCAL"]) + b"\n", after
        if line.translate(None, _TEXT_BYTES) and (   # bytes no header holds: its voxel data, read as lines
                not sep or not _FIELD_NAME.fullmatch(key) or value.translate(None, _TEXT_BYTES + _HIGH_BYTES)):
            raise UnsupportedFile(f"{filename}: an MHA header with no ElementDataFile line before its voxel data")
        if line.translate(None, _TEXT_BYTES):       # a field in another script: one the service reads is refused
            if name in MHA_FIELDS or name in MHA_YES_NO or name == "headersize":
                raise UnsupportedFile(f"{filename}: the MHA header's {MHA_CANONICAL.get(name, name)} holds bytes "
                                      "that are not ASCII")
            continue
        if _DETACHED.search(key) or b"\r" in line:      # a \r inside a line: no field of any reader's
            raise _detached(filename, "mha") if _DETACHED.search(line) else UnsupportedFile(
                f"{filename}: an MHA header line with a carriage return inside it")
        if sep and name == "headersize":      # the data follow the rebuilt header: a skip into it is refused
            if value.strip() not in (b"-1", b"0"):
                raise UnsupportedFile(f"{filename}: an MHA header with a HeaderSize (bytes to skip before the data) "
                                      "other than 0 or -1")
            continue
        if sep and name in MHA_YES_NO:        # as MetaIO reads it: T, t or 1 first is yes, anything else no
            out.append(MHA_CANONICAL[name].encode() + (b" = True" if value.strip()[:1] in (b"T", b"t", b"1")
                                                        else b" = False"))
        elif sep and name in MHA_FIELDS:
            out.append(MHA_CANONICAL[name].encode() + b" = " + value.strip())
    return b"", None


MET_ITEM_BYTES = {"MET_CHAR": 1, "MET_UCHAR": 1, "MET_SHORT": 2, "MET_USHORT": 2, "MET_INT": 4, "MET_UINT": 4,
                  "MET_LONG": 8, "MET_ULONG": 8, "MET_LONG_LONG": 8, "MET_ULONG_LONG": 8, "MET_FLOAT": 4,
                  "MET_DOUBLE": 8}
"""Bytes of one value by MetaImage ``ElementType`` (``long`` as ITK builds it on 64-bit Linux and macOS)."""


def _inflated_mha(header: bytes, data: bytes, src: BinaryIO, dst: BinaryIO, filename: str,
                  max_bytes: int) -> None:
    """Write a compressed MetaImage as an uncompressed one: its header marked so, then its data
    inflated here, bounded by the values the header declares. ITK's reader leaves the voxels of a
    stream that fails to inflate as the memory it allocated held (an earlier upload's voxels, say)
    and says nothing; here a stream that is corrupt, cut short or longer than declared is refused."""
    item = MET_ITEM_BYTES[header_fields(header, "mha")["elementtype"].decode("latin-1").strip().upper()]
    expected = declared_values(header, "mha", filename) * item
    if expected <= 0:
        raise UnsupportedFile(f"{filename}: a compressed MHA file that declares {expected} bytes of voxel data")
    if expected > max_bytes:                 # refused as every decoder refuses its bomb: before it inflates
        raise PayloadTooLarge(f"{filename}: its header declares {expected:,} bytes of voxel data (a compressed MHA "
                              f"file), more than the {max_bytes / 2**20:.3g} MB one file may decode to")
    kept = [line for line in header.split(b"\n") if not line.startswith((b"CompressedData", b"ElementDataFile"))]
    dst.write(b"\n".join(kept[:-1] + [b"CompressedData = False", b"ElementDataFile = LOCAL"]) + b"\n")
    inflater, written = zlib.decompressobj(zlib.MAX_WBITS | 32), 0      # zlib or gzip, as ITK reads them
    try:
        chunk = data or src.read(1 << 20)
        while chunk and not inflater.eof:
            out = inflater.decompress(chunk, expected + 1 - written)
            written += len(out)
            if written > expected:
                break
            dst.write(out)
            chunk = inflater.unconsumed_tail or src.read(1 << 20)
    except zlib.error:
        written = -1
    if written != expected or not inflater.eof:
        raise UnsupportedFile(f"{filename}: compressed MHA data that do not inflate to the {expected} bytes its "
                              "header declares (corrupt or truncated)")


__all__ = ["MAX_HEADER_BYTES", "clean_header", "declared_grid", "declared_values", "header_fields"]
