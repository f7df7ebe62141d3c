"""A ZIP archive holding one DICOM series, unpacked with every decoder bounded.

* The member list's size is read from the archive's end record and its entries are counted by
  their fixed headers, both bounded before the ZIP reader parses the list.
* Members are inflated in chunks to flat, numbered files of a private folder (archive paths are never
  used), each chunk charged to the upload's :class:`~service.io.limits.FileBudget`.
* A member that is itself an archive (ZIP, gzip, bzip2, xz, 7z, RAR) is refused by name: nothing nested
  is ever decoded.
* Each DICOM member goes through :func:`service.io.dicom_guard.load_dataset` (deflate bounded, pixel data
  checked against the budget and compressed frames against the header) before GDCM sees it; a deflated
  member is handed to GDCM already inflated, so GDCM never inflates anything itself. Members that are
  not DICOM files with pixel data (a README, a DICOMDIR) are left out.
* The series' files must make one stack (:mod:`service.io.acquisition_geometry`: orientation, pixel spacing
  and positions present, alike and evenly spaced), or the archive is refused (422).

Every message names the client's archive and, where it is about one member, the member.
"""

from __future__ import annotations

import struct
import tempfile
import zipfile
import zlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from pydicom import uid

from service.core.errors import PayloadTooLarge, UnsupportedFile, UnusableImage
from service.io.acquisition_geometry import Tags, series_problem, stated_thickness
from service.io.acquisition_times import order_of, seconds
from service.io.dicom import read_dicom_file
from service.io.dicom_guard import load_dataset
from service.io.bare_dicom import as_part10, bare_dicom
from service.io.limits import FileBudget, raise_if_out_of_space
from service.io.volume import SITK_FILES, Volume, from_sitk

MAX_MEMBERS = 5000
MAX_DIRECTORY_BYTES = 16 * 2**20
"""The most bytes of member list (central directory) parsed: 5,000 entries of about 3 KB each."""
ARCHIVE_MAGIC = (b"PK\x03\x04", b"PK\x05\x06", b"\x1f\x8b", b"BZh", b"\xfd7zXZ", b"7z\xbc\xaf", b"Rar!")


def _check_directory(path: Path, filename: str) -> None:
    """Refuse an archive with more than :data:`MAX_MEMBERS` members or a member list over
    :data:`MAX_DIRECTORY_BYTES`, before the ZIP reader parses the list (which takes time and memory
    in proportion to its entries). The list's size comes from the end record and its entries are
    counted by their fixed headers, so an end record that understates the count is not believed.
    An end record that cannot be read is left to the ZIP reader to refuse."""
    with open(path, "rb") as f:
        try:
            end = zipfile._EndRecData(f)              # the end record the ZIP reader itself uses (ZIP64 too)
        except (OSError, ValueError, struct.error):
            return
        if end is None:
            return
        count, size = int(end[zipfile._ECD_ENTRIES_TOTAL]), int(end[zipfile._ECD_SIZE])
        if count > MAX_MEMBERS or size > MAX_DIRECTORY_BYTES:
            raise UnusableImage(f"{filename}: too many files in the archive ({count} members, a member list of "
                                f"{size} bytes)")
        start = int(end[zipfile._ECD_LOCATION]) - size            # where the ZIP reader looks for the list
        if end[zipfile._ECD_SIGNATURE] == zipfile.stringEndArchive64:
            start -= zipfile.sizeEndCentDir64 + zipfile.sizeEndCentDir64Locator
        if start < 0:
            return
        f.seek(start)
        listed = _entries(f.read(size))
    if listed > MAX_MEMBERS:
        raise UnusableImage(f"{filename}: too many files in the archive (more than {MAX_MEMBERS} members in a "
                            f"member list of {size} bytes)")


def _entries(directory: bytes) -> int:
    """The entries of a ZIP member list, counted by their 46-byte fixed headers up to one more than
    :data:`MAX_MEMBERS` (the rest of the list is not looked at).

    Example (one entry named ``a``):
        >>> _entries(b"PK\\x01\\x02" + bytes(24) + b"\\x01\\x00" + bytes(16) + b"a")
        1
    """
    count = position = 0
    while count <= MAX_MEMBERS and position + 46 <= len(directory) and directory[position:position + 4] == b"PK\x01\x02":
        name, extra, comment = struct.unpack_from("<HHH", directory, position + 28)
        position += 46 + name + extra + comment
        count += 1
    return count


GEOMETRY_TOLERANCE = 1e-4
"""How far (relative) GDCM's reading of a file's position, orientation and pixel spacing may lie
from pydicom's: the decimal strings' rounding, not another value."""


def read_dicom_zip(path: Path, filename: str, budget: FileBudget, scratch: Path | None = None) -> Volume:
    """The one DICOM series inside the ZIP archive ``path`` (the client's ``filename``), its members
    unpacked into a temporary folder in ``scratch`` (default: the system's)."""
    with tempfile.TemporaryDirectory(prefix="svrnet-zip-", dir=scratch) as tmp:
        labels: dict[str, str] = {}           # unpacked file -> "archive.zip: member" (for messages)
        times: dict[str, float | None] = {}   # unpacked file -> its acquisition time (for the order only)
        thicknesses: dict[str, object] = {}     # unpacked file -> its SliceThickness
        tags: dict[str, Tags] = {}            # unpacked file -> its geometry tags (to check the series)
        sizes: dict[str, tuple[int, ...]] = {}  # unpacked file -> (columns, rows, frames) as pydicom read them
        try:
            _check_directory(path, filename)
            with zipfile.ZipFile(path) as z:
                members = [m for m in z.infolist() if m.filename and not m.is_dir()]   # a nameless one: no file
                if len(members) > MAX_MEMBERS:
                    raise UnusableImage(f"{filename}: too many files in the archive ({len(members)})")
                if sum(m.file_size for m in members) > budget.limit:
                    raise budget.too_large("the archive inflates")
                for i, m in enumerate(members):
                    # By its place alone: scanners name members (and folders) after the patient and the date.
                    label = f"{filename}: member {i + 1} of {len(members)}"
                    out = Path(tmp) / f"{i:05d}.dcm"
                    if _unpack(z, m, out, budget.member(label), label, times, tags, thicknesses, sizes):
                        labels[str(out)] = label
                        budget.slices(len(labels), "DICOM images in the archive or more (counted as they are read)")
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError) as exc:
            raise_if_out_of_space(exc)
            raise UnsupportedFile(f"{filename}: corrupt or truncated ZIP archive") from exc
        except (NotImplementedError, RuntimeError) as exc:     # an unknown method, an encrypted member
            raise UnsupportedFile(f"{filename}: a ZIP archive with encrypted members or an unsupported "
                                  "compression method") from exc
        reader = sitk.ImageSeriesReader()
        with SITK_FILES:
            series = reader.GetGDCMSeriesIDs(tmp) if labels else ()
        if not series:
            raise UnsupportedFile(f"{filename}: the ZIP archive holds no DICOM series")
        if len(series) > 1:
            raise UnusableImage(f"{filename}: the ZIP archive holds {len(series)} DICOM series; upload one per file")
        with SITK_FILES:
            files = reader.GetGDCMSeriesFileNames(tmp, series[0])
        if len(files) == 1:                  # read again as a file of its own: its voxels charged to it alone
            label = labels.get(files[0], filename)
            return read_dicom_file(Path(files[0]), label, budget.request.file(label))
        if (many := sum(sizes[f][2] > 1 for f in files)):
            raise UnusableImage(f"{filename}: a DICOM series of {len(files)} files, {many} of them multi-frame; "
                                "a multi-frame file is a stack of its own: upload it as one")
        if (problem := series_problem([tags[f] for f in files])) is not None:
            raise UnusableImage(f"{filename}: a DICOM series of {len(files)} files, but {problem}")
        for f in files:
            _check_size(f, sizes[f], tags[f], labels.get(f, filename))
        reader.SetFileNames(files)
        reader.SetOutputPixelType(sitk.sitkFloat32)   # each file's own rescale kept: else the first file's type
        with SITK_FILES:
            image = reader.Execute()
        return replace(from_sitk(image), acquisition_order=order_of([times.get(f) for f in files]),
                       slice_thickness_mm=stated_thickness([thicknesses.get(f) for f in files]))


def _check_size(path: str, size: tuple[int, ...], tags: Tags, label: str) -> None:
    """Refuse a file whose image size or geometry GDCM, which builds the series' volume, reads
    otherwise than pydicom, whose reading was checked and charged (``size``: columns, rows, frames)
    and whose tags the series' checks passed (``tags``: position, orientation, pixel spacing): a
    header that states Rows, Columns or a geometry tag twice is read by its first value in one and
    its last in the other, so a small archive could make GDCM build a volume far larger than the
    one charged, or place its slices where no check looked (reversed, a slice missing, sheared)."""
    info = sitk.ImageFileReader()
    info.SetImageIO("GDCMImageIO")
    info.SetFileName(path)
    with SITK_FILES:
        info.ReadImageInformation()
    found = info.GetSize()
    if tuple(found[:2]) != size[:2] or int(np.prod(found[2:], dtype=np.int64)) != size[2]:
        raise UnsupportedFile(f"{label}: a DICOM header that states the image size twice, differently")
    position, orientation, spacing = (np.asarray(t, np.float64) for t in tags)      # checked: present, finite
    unit = lambda v: (v.reshape(2, 3) / np.linalg.norm(v.reshape(2, 3), axis=1, keepdims=True)).reshape(-1)  # noqa: E731
    axes = np.asarray(info.GetDirection(), np.float64).reshape(3, 3)[:, :2].T.reshape(-1)
    stated = np.concatenate([position, unit(orientation), spacing[::-1]])
    read = np.concatenate([info.GetOrigin(), unit(axes), info.GetSpacing()[:2]])
    if np.abs(read - stated).max() > GEOMETRY_TOLERANCE * max(1.0, float(np.abs(stated).max())):
        raise UnsupportedFile(f"{label}: a DICOM header that states its position, orientation or pixel spacing "
                              "twice, differently")


def _unpack(z: zipfile.ZipFile, member: zipfile.ZipInfo, out: Path, budget: FileBudget, label: str,
            times: dict[str, float | None], tags: dict[str, Tags], thicknesses: dict[str, object],
            sizes: dict[str, tuple[int, ...]]) -> bool:
    """Inflate ``member`` to ``out`` (charged to ``budget``) and screen it: whether it is a DICOM
    image (kept; a data set without the file preamble, :func:`bare_dicom`, kept as a DICOM file) or
    not (removed again).
    Its acquisition time goes to ``times`` (:mod:`service.io.acquisition_times`), its geometry tags
    to ``tags`` (:mod:`service.io.acquisition_geometry`), its slice thickness to ``thicknesses``, its
    image size to ``sizes``."""
    with z.open(member) as src, open(out, "wb") as dst:
        while chunk := src.read(1 << 20):
            budget.inflate(len(chunk))
            dst.write(chunk)
    with open(out, "rb") as f:
        head = f.read(1024)                   # the preamble, or a bare data set's first elements
    if head.startswith(ARCHIVE_MAGIC):
        raise UnsupportedFile(f"{label}: an archive nested in the archive; upload the DICOM files of one "
                              "series in a single ZIP")
    if head[128:132] != b"DICM":
        if not bare_dicom(head):
            out.unlink()
            return False
        as_part10(out, out.with_suffix(".part10"), label)
        out.with_suffix(".part10").replace(out)
    try:
        ds = load_dataset(out, label, budget, require_pixels=False)
    except (PayloadTooLarge, UnsupportedFile, UnusableImage):    # a 422 says what is wrong with it
        raise
    except Exception as exc:  # noqa: BLE001 - pydicom's errors on a client's bytes
        raise UnsupportedFile(f"{label}: unreadable DICOM file") from exc
    if "PixelData" not in ds:
        out.unlink()
        return False
    times[str(out)] = seconds(ds)
    thicknesses[str(out)] = ds.get("SliceThickness")
    sizes[str(out)] = (int(ds.Columns), int(ds.Rows), int(getattr(ds, "NumberOfFrames", 1) or 1))   # checked by load_dataset
    tags[str(out)] = (ds.get("ImagePositionPatient"), ds.get("ImageOrientationPatient"), ds.get("PixelSpacing"))
    if ds.file_meta.TransferSyntaxUID == uid.ExplicitVRLittleEndian and _was_deflated(out):
        ds.save_as(out, implicit_vr=False, little_endian=True, enforce_file_format=True)
    return True


def _was_deflated(path: Path) -> bool:
    """Whether the file on disk still says Deflated Explicit VR Little Endian (then it is rewritten)."""
    with open(path, "rb") as f:
        return uid.DeflatedExplicitVRLittleEndian.encode() in f.read(1024)


__all__ = ["MAX_MEMBERS", "read_dicom_zip"]
