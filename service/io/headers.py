"""Text headers of NRRD and MetaImage uploads, rewritten so that a reader can only see the upload's bytes.

NRRD and MetaImage headers may name another file that holds the voxel data (``data file:`` in NRRD,
``ElementDataFile = <path>`` in MetaImage). A client's header must never make the server open one of
its own files, so an upload is never handed to a reader as sent:

* the whole header is parsed, however long (up to :data:`MAX_HEADER_BYTES`; a longer one is refused);
* a header that names another file anywhere -- whatever the spelling, case or position of the field,
  existing path or not -- is refused with the same 415, so the answer tells nothing about the server;
* the reader gets a *new* header written here from an allow-list of geometry and encoding fields,
  followed by the upload's own data bytes: fields that could name a file are never copied.

Example:
    >>> import io
    >>> src = io.BytesIO(b"NRRD0004\\n# note\\ntype: uchar\\ndimension: 1\\nsizes: 2\\nencoding: raw\\n\\n\\x01\\x02")
    >>> dst = io.BytesIO(); clean_header(src, dst, "nrrd", "a.nrrd")
    >>> dst.getvalue()
    b'NRRD0004\\ntype: uchar\\ndimension: 1\\nsizes: 2\\nencoding: raw\\n\\n\\x01\\x02'
"""

from __future__ import annotations

import re
import shutil
from typing import BinaryIO

from service.core.errors import UnsupportedFile

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


def _lines(head: bytes) -> list[tuple[bytes, int]]:
    """Each line of ``head`` (without its ``\\r\\n``) and the offset just after it."""
    out, pos = [], 0
    while pos < len(head):
        end = head.find(b"\n", pos)
        nxt = len(head) if end < 0 else end + 1
        out.append((head[pos:nxt].rstrip(b"\r\n"), nxt))
        pos = nxt
    return out


def clean_header(src: BinaryIO, dst: BinaryIO, kind: str, filename: str) -> None:
    """Copy an NRRD (``kind="nrrd"``) or MetaImage (``"mha"``) upload from ``src`` to ``dst`` with a
    header rebuilt from allowed fields; its data bytes are copied unchanged.

    Raises:
        UnsupportedFile: the header names another file, is longer than :data:`MAX_HEADER_BYTES`, or
            is incomplete (no data follow it). The message names ``filename`` only.
    """
    head = src.read(MAX_HEADER_BYTES + 1)
    complete = len(head) <= MAX_HEADER_BYTES
    lines = _lines(head)
    header, data_at = (_nrrd if kind == "nrrd" else _mha)(lines, filename)
    if data_at is None:
        # No end of header: the whole (allowed) prefix is header. Any reference to a file refuses it,
        # whether or not the header would be complete; otherwise it is too long or has no data.
        if any(_DETACHED.search(line.split(b":", 1)[0].split(b"=", 1)[0]) for line, _ in lines):
            raise _detached(filename, kind)
        if not complete:
            raise UnsupportedFile(f"{filename}: a {kind.upper()} header longer than {MAX_HEADER_BYTES >> 10} KB")
        raise UnsupportedFile(f"{filename}: a {kind.upper()} header with no voxel data after it")
    dst.write(header)
    dst.write(head[data_at:])
    shutil.copyfileobj(src, dst, 1 << 20)


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
        if _DETACHED.search(key):
            raise _detached(filename, "mha")
        if sep and name in MHA_FIELDS:
            out.append(MHA_CANONICAL[name].encode() + b" = " + value.strip())
    return b"", None


__all__ = ["MAX_HEADER_BYTES", "clean_header"]
