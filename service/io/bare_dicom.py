"""DICOM data sets stored without the file preamble: recognised from their first elements
(:func:`bare_dicom`) and rewritten as DICOM files (Part 10) that the readers take as any other
(:func:`as_part10`).

Older archives and some exports store a data set as it is, without the 128-byte preamble, ``DICM``
and the file-meta group that names its encoding (the ACR-NEMA way). Such a data set is read by the
encoding its first element shows: an explicit VR after the tag, or else implicit VR; little endian,
as every data set without a file-meta group is. The rewritten file gets the file-meta group that
encoding needs, its SOP class and instance copied from the data set, and the data set's bytes as
they were.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from pydicom import uid
from pydicom.dataset import FileMetaDataset
from pydicom.filebase import DicomFileLike
from pydicom.filereader import read_dataset
from pydicom.filewriter import write_file_meta_info

from service.core.errors import UnsupportedFile
from service.io.dicom_structure import LONG_VRS, UNDEFINED, check_structure

SOP_INSTANCE_UID = 0x00080018
"""The last element of the data set read for its file-meta group (its SOP class comes just before)."""

VRS = frozenset(b"AE AS AT CS DA DS DT FD FL IS LO LT OB OD OF OL OV OW PN SH SL SQ SS ST SV TM UC UI UL UN UR "
                b"US UT UV".split())
"""The value representations of an explicit-VR element (:data:`LONG_VRS` among them)."""
BARE_ELEMENTS = 4
"""Elements of a bare data set's start walked (within the bytes read) before it is called one."""


def bare_dicom(head: bytes) -> bool:
    """Whether ``head`` (a file's first bytes) starts like a DICOM data set stored without the file
    preamble: a little-endian tag of the file-meta (0002) or identifying (0008) group, then, for as
    many of the first :data:`BARE_ELEMENTS` elements as ``head`` holds, an explicit VR or an
    implicit element's length under 64 KB, each value of even length (a group's length 4 bytes) and
    each tag after the one before it (the file-meta group is walked alone: the data set after it
    may change its encoding). Two bytes ``08 00`` at a file's start alone, as a raw array starting
    with the number 8 has them, are no DICOM.

    Example:
        >>> bare_dicom(b"\\x08\\x00\\x05\\x00CS\\x0a\\x00ISO_IR 100"), bare_dicom(b"\\x08\\x00\\x16\\x00\\x1a\\x00\\x00\\x00")
        (True, True)
        >>> bare_dicom(b"hello world, not an image"), bare_dicom(b"\\x08\\x00")
        (False, False)
        >>> bare_dicom((8).to_bytes(4, "little") + (16).to_bytes(4, "little") + bytes(range(40)))  # uint32s
        False
    """
    if len(head) < 8 or head[:2] not in (b"\x02\x00", b"\x08\x00"):
        return False
    explicit = head[4:6] in VRS
    at, last = 0, (-1, -1)
    for _ in range(BARE_ELEMENTS):
        if at + 8 > len(head):
            break
        tag = (int.from_bytes(head[at:at + 2], "little"), int.from_bytes(head[at + 2:at + 4], "little"))
        if last[0] == 2 and tag[0] != 2:        # the file-meta group walked: the data set may be encoded otherwise
            return tag > last
        if tag <= last:
            return False
        if not explicit:
            length, at = int.from_bytes(head[at + 4:at + 8], "little"), at + 8
        elif (vr := head[at + 4:at + 6]) not in VRS:
            return False
        elif vr in LONG_VRS:
            if head[at + 6:at + 8] != b"\0\0":
                return False
            if at + 12 > len(head):
                break
            length, at = int.from_bytes(head[at + 8:at + 12], "little"), at + 12
        else:
            length, at = int.from_bytes(head[at + 6:at + 8], "little"), at + 8
        if length == UNDEFINED:                 # a sequence or item of undefined length: its items follow
            break
        if length % 2 or (not explicit and length >= 1 << 16) or (tag[1] == 0 and length != 4):
            return False                        # an odd length, a header's value that long, a group length not a UL
        at, last = at + length, tag
    return True


def as_part10(src: Path, dst: Path, filename: str) -> None:
    """Write the bare data set ``src`` (:func:`bare_dicom`) to ``dst`` as a DICOM file: the preamble,
    ``DICM``, a file-meta group (its own where the data set starts with one) and the data set.

    Its elements are counted before pydicom reads any (:func:`~service.io.dicom_structure.check_structure`);
    pydicom then reads only its first group, up to the SOP instance UID.

    Raises:
        UnsupportedFile: a data set whose first elements pydicom cannot read (naming ``filename``).
    """
    with open(src, "rb") as fp:
        head = fp.read(12)
        fp.seek(0)
        with open(dst, "wb") as out:
            out.write(b"\0" * 128 + b"DICM")
            if head[:2] != b"\x02\x00":               # no file-meta group of its own: one is written
                implicit = head[4:6] not in VRS
                check_structure(fp, filename, implicit, True)
                try:
                    first = read_dataset(fp, implicit, True, stop_when=lambda tag, vr, length: tag > SOP_INSTANCE_UID)
                    sop_class, sop_instance = first.get("SOPClassUID"), first.get("SOPInstanceUID")
                except Exception as exc:  # noqa: BLE001 - pydicom's errors on a client's bytes
                    raise UnsupportedFile(f"{filename}: a DICOM data set without the file preamble whose first "
                                          "elements are unreadable") from exc
                meta = FileMetaDataset()
                meta.MediaStorageSOPClassUID = sop_class or uid.MRImageStorage
                meta.MediaStorageSOPInstanceUID = sop_instance or uid.generate_uid()
                meta.TransferSyntaxUID = uid.ImplicitVRLittleEndian if implicit else uid.ExplicitVRLittleEndian
                meta.ImplementationClassUID = uid.PYDICOM_IMPLEMENTATION_UID
                write_file_meta_info(DicomFileLike(out), meta, enforce_standard=True)
                fp.seek(0)
            shutil.copyfileobj(fp, out)
