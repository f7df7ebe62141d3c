"""A DICOM dataset's elements counted from its bytes, before pydicom builds any of them.

pydicom makes a Python object of every element and sequence item it reads: hundreds of bytes for an
element of eight, so a file of a few hundred KB of empty items or zero-length elements would take
gigabytes, at any depth and after the pixel data too. :func:`check_structure` walks the dataset's
raw bytes as pydicom reads them (tag, VR, length; into sequences and items, over every other
value) and refuses a dataset of more than :data:`MAX_ELEMENTS` elements and items, or of more than
:data:`MAX_HEADER_BYTES` before its pixel data, holding nothing but a stack of open containers.
Where the bytes stop making sense (a length past the end, a stray tag) it stops counting: pydicom's
own reading then says what is wrong, as it always has.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import BinaryIO

from pydicom.datadict import dictionary_VR
from pydicom.filereader import ENCODED_VR

from service.core.errors import PayloadTooLarge, UnsupportedFile

MAX_ELEMENTS = 200_000
"""The most elements and sequence items in one file, at every depth (an enhanced MR file of a
thousand frames holds about a hundred thousand)."""
MAX_HEADER_BYTES = 8 << 20
"""The most bytes of a dataset before its pixel data."""
MAX_META_ELEMENTS = 1_000
"""The most elements of a file-meta group (group 0002; the standard defines twelve)."""
PIXEL_DATA = 0x7FE00010
UNDEFINED = 0xFFFFFFFF
LONG_VRS = frozenset({b"OB", b"OD", b"OF", b"OL", b"OV", b"OW", b"SQ", b"SV", b"UC", b"UN", b"UR", b"UT", b"UV"})
"""Explicit VRs whose length takes 4 bytes (after 2 reserved)."""
ITEM, ITEM_END, SEQUENCE_END = 0xE000, 0xE00D, 0xE0DD


@dataclass
class _Open:
    """A container the walk is inside: a dataset (the file's, or an item's) or a sequence of items;
    ``end``: its last byte + 1 where its length is defined; ``implicit``: its elements' VR encoding.
    An element of undefined length that is no sequence (encapsulated pixel data) is no container:
    pydicom takes its value up to the next sequence delimiter, and so does the walk
    (:func:`_past_delimiter`)."""

    kind: str
    end: int | None
    implicit: bool


def _is_sequence(tag: int) -> bool:
    try:
        return dictionary_VR(tag) == "SQ"
    except KeyError:
        return False


def check_structure(fp: BinaryIO, filename: str, implicit_vr: bool, little_endian: bool) -> None:
    """Refuse (413) the dataset that starts at ``fp``'s position (left there again) when it holds more
    than :data:`MAX_ELEMENTS` elements and items or more than :data:`MAX_HEADER_BYTES` before its
    pixel data (see the module).

    Example (an explicit VR little endian dataset: a sequence of 5 empty items, then pixel data):
        >>> import io, struct
        >>> items = struct.pack("<HH2sHI", 8, 0x1140, b"SQ", 0, UNDEFINED) + struct.pack("<HHI", 0xFFFE, ITEM, 0) * 5
        >>> pixels = b"\\xe0\\x7f\\x10\\x00OW\\x00\\x00" + struct.pack("<I", 2) + b"\\x01\\x00"
        >>> data = items + struct.pack("<HHI", 0xFFFE, SEQUENCE_END, 0) + pixels
        >>> check_structure(io.BytesIO(data), "a.dcm", False, True)
        >>> try:
        ...     check_structure(io.BytesIO(items + items[12:20] * MAX_ELEMENTS), "b.dcm", False, True)
        ... except PayloadTooLarge as exc:
        ...     print(exc.detail)
        b.dcm: a DICOM dataset of more than 200000 elements and sequence items
    """
    start = fp.tell()
    size = fp.seek(0, 2) - start
    fp.seek(start)
    try:
        _walk(fp, start, size, filename, implicit_vr, "<" if little_endian else ">")
    finally:
        fp.seek(start)


def check_file_meta(fp: BinaryIO, filename: str) -> None:
    """Refuse (413) the file-meta group that starts at ``fp``'s position (left there again) when it
    holds more than :data:`MAX_META_ELEMENTS` elements, counted as pydicom reads them: explicit VR,
    an element whose VR is no two capitals read as implicit VR (pydicom's switch), and the whole
    group as implicit VR too where its first element's VR is no known one (pydicom reads it again so).
    An element of undefined length is refused (415): pydicom would read on past it, and no element of
    the group has one. pydicom reads the group whole before the dataset's own count
    (:func:`check_structure`) can start, every element a Python object.

    Example (a group of two elements, then the dataset's first tag):
        >>> import io, struct
        >>> meta = struct.pack("<HH2sHI", 2, 0, b"UL", 4, 30) + struct.pack("<HH2sH", 2, 0x10, b"UI", 20) + bytes(20)
        >>> check_file_meta(io.BytesIO(meta + struct.pack("<HH", 8, 0x16)), "a.dcm")
        >>> try:
        ...     check_file_meta(io.BytesIO(struct.pack("<HH2sH", 2, 0x10, b"UI", 0) * 2000), "b.dcm")
        ... except PayloadTooLarge as exc:
        ...     print(exc.detail)
        b.dcm: a DICOM file-meta group of more than 1000 elements
    """
    start = fp.tell()
    try:
        first = fp.read(8)
        _count_meta(fp, start, filename, False)
        if len(first) == 8 and first[4:6] not in ENCODED_VR:
            _count_meta(fp, start, filename, True)
    finally:
        fp.seek(start)


def _count_meta(fp: BinaryIO, start: int, filename: str, implicit: bool) -> None:
    fp.seek(start)
    for _ in range(MAX_META_ELEMENTS + 1):
        head = fp.read(8)
        if len(head) < 8 or struct.unpack("<H", head[:2])[0] != 2:
            return
        if (read := _vr_and_length(fp, head, implicit, "<")) is None:
            return
        _, length, _ = read
        if length == UNDEFINED:
            group, element = struct.unpack("<HH", head[:4])
            raise UnsupportedFile(f"{filename}: a DICOM file-meta element ({group:04X},{element:04X}) of undefined "
                                  "length (the file-meta group's elements have defined lengths)")
        fp.seek(length, 1)
    raise PayloadTooLarge(f"{filename}: a DICOM file-meta group of more than {MAX_META_ELEMENTS} elements")


def _vr_and_length(fp: BinaryIO, head: bytes, implicit: bool, e: str) -> tuple[bytes | None, int, int] | None:
    """An element's VR (None: read as implicit VR), value length and header bytes, from its first 8
    bytes ``head`` (and the 4 that follow a long VR's, read from ``fp``), as pydicom reads them; None
    where the file ends first.

    Example (a short VR, and VR bytes that are no two capitals: implicit VR, a 4-byte length):
        >>> import io
        >>> _vr_and_length(io.BytesIO(), struct.pack("<HH2sH", 8, 0x16, b"UI", 20), False, "<")
        (b'UI', 20, 8)
        >>> _vr_and_length(io.BytesIO(), struct.pack("<HHI", 8, 0x16, 20), False, "<")
        (None, 20, 8)
    """
    if implicit or _switches_to_implicit(head[4:6]):
        return None, struct.unpack(e + "I", head[4:])[0], 8
    vr = head[4:6]
    if vr in LONG_VRS:
        if len(long := fp.read(4)) < 4:
            return None
        return vr, struct.unpack(e + "I", long)[0], 12
    return vr, struct.unpack(e + "H", head[6:])[0], 8


def _switches_to_implicit(vr: bytes) -> bool:
    """Whether pydicom reads an element of an explicit VR dataset whose VR bytes are ``vr`` as implicit
    VR (tag, then a 4-byte length): where they are no two capital letters."""
    return not b"AA" <= vr <= b"ZZ"


def _past_delimiter(fp: BinaryIO, e: str) -> bool:
    """Move ``fp`` past the next sequence delimiter (its tag and 4-byte length), as pydicom reads an
    element of undefined length that is no sequence: its value is every byte up to that tag. False
    (``fp`` anywhere) where the file holds none.

    Example:
        >>> import io
        >>> fp = io.BytesIO(b"\x01\x02" + struct.pack("<HHI", 0xFFFE, SEQUENCE_END, 0) + b"next")
        >>> _past_delimiter(fp, "<"), fp.read()
        (True, b'next')
    """
    delimiter = struct.pack(e + "HH", 0xFFFE, SEQUENCE_END)
    tail = b""
    while chunk := fp.read(1 << 20):
        data = tail + chunk
        if (found := data.find(delimiter)) >= 0:
            fp.seek(found - len(data) + len(delimiter) + 4, 1)
            return True
        tail = data[-(len(delimiter) - 1):]
    return False


def _walk(fp: BinaryIO, start: int, size: int, filename: str, implicit: bool, e: str) -> None:
    stack = [_Open("dataset", size, implicit)]
    count = 0
    while True:
        at = fp.tell() - start
        while stack and stack[-1].end is not None and at >= stack[-1].end:
            stack.pop()                                  # a container of defined length ends here
        head = fp.read(8)
        if not stack or len(head) < 8:
            return
        group, element = struct.unpack(e + "HH", head[:4])
        count += 1
        if count > MAX_ELEMENTS:
            raise PayloadTooLarge(f"{filename}: a DICOM dataset of more than {MAX_ELEMENTS} elements and sequence items")
        top = stack[-1]
        if group == 0xFFFE:                              # items and delimiters: tag and a 4-byte length, no VR
            length = struct.unpack(e + "I", head[4:])[0]
            if element == SEQUENCE_END and top.kind == "sequence":
                stack.pop()
            elif element == ITEM_END and top.kind == "dataset" and len(stack) > 1:
                stack.pop()
            elif element == ITEM and top.kind == "sequence":
                stack.append(_Open("dataset", None if length == UNDEFINED else at + 8 + length, top.implicit))
            else:
                return                                   # no structure pydicom reads: it says what is wrong
            continue
        if top.kind != "dataset":
            return
        tag = group << 16 | element
        if (read := _vr_and_length(fp, head, top.implicit, e)) is None:
            return                                       # cut short: pydicom's reading says so
        vr, length, header = read
        if tag == PIXEL_DATA and len(stack) == 1 and at > MAX_HEADER_BYTES:
            raise PayloadTooLarge(f"{filename}: a DICOM header of more than {MAX_HEADER_BYTES >> 20} MB before its "
                                  "pixel data")
        end = None if length == UNDEFINED else at + header + length
        if vr == b"SQ" or (vr in (None, b"UN") and tag != PIXEL_DATA and (length == UNDEFINED or _is_sequence(tag))):
            stack.append(_Open("sequence", end, top.implicit or vr == b"UN"))   # a UN sequence is implicit VR
        elif length == UNDEFINED:          # encapsulated pixel data too: pydicom takes the bytes up to the delimiter
            if not _past_delimiter(fp, e):
                return
        elif end > size:
            return
        else:
            fp.seek(length, 1)
        if len(stack) == 1 and fp.tell() - start > MAX_HEADER_BYTES and tag < PIXEL_DATA:
            raise PayloadTooLarge(f"{filename}: a DICOM header of more than {MAX_HEADER_BYTES >> 20} MB before its "
                                  "pixel data")
