"""Uploaded files -> :class:`Volume`, recognised by content (magic bytes), not by file name.

Formats: NIfTI (``.nii``, ``.nii.gz``), NRRD, MetaImage (``.mha``), a single DICOM file (classic,
Enhanced multi-frame, or Siemens mosaic), or a ``.zip`` holding one DICOM series. DICOM files are
de-identified on read: only pixel data and geometry leave this module, no tag values are logged.

Validation (each failure raises with the file's name, never a tag value):
* unreadable, truncated or unknown -> :class:`UnsupportedFile` (415);
* 2D, 4D with more than one volume, empty, or non-finite values -> :class:`UnusableImage` (422).
"""

from __future__ import annotations

import gzip
import tempfile
import zipfile
import zlib
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from service.core.errors import UnsupportedFile, UnusableImage
from service.io.volume import Volume, from_sitk

SUFFIX_BY_KIND = {"nifti": ".nii", "nifti-gz": ".nii.gz", "nrrd": ".nrrd", "mha": ".mha"}


def sniff(path: Path) -> str:
    """The kind of file: ``nifti``, ``nifti-gz``, ``nrrd``, ``mha``, ``dicom``, ``zip`` or ``unknown``."""
    with open(path, "rb") as f:
        head = f.read(1024)
    if head[:2] == b"\x1f\x8b":
        try:
            with gzip.open(path, "rb") as g:
                inner = g.read(352)
                while g.read(1 << 22):  # to the end: a truncated stream or a bad CRC raises here
                    pass
        except (OSError, EOFError, zlib.error):
            return "unknown"
        return "nifti-gz" if _is_nifti(inner) else "unknown"
    if _is_nifti(head):
        return "nifti"
    if head.startswith(b"NRRD000"):
        return "nrrd"
    if b"ObjectType" in head[:200] and b"NDims" in head:
        return "mha"
    if head[128:132] == b"DICM":
        return "dicom"
    if head[:4] == b"PK\x03\x04":
        return "zip"
    return "unknown"


def _is_nifti(head: bytes) -> bool:
    if len(head) < 348:
        return False
    sizeof = int.from_bytes(head[:4], "little"), int.from_bytes(head[:4], "big")
    return (348 in sizeof and head[344:348] in (b"n+1\x00", b"ni1\x00")) or 540 in sizeof


def read_upload(path: Path, filename: str) -> Volume:
    """Read one uploaded file as a 3D :class:`Volume`; ``filename`` is used in error messages only."""
    kind = sniff(path)
    try:
        if kind in SUFFIX_BY_KIND:
            # SimpleITK picks its reader by suffix: give it a link named by the sniffed content.
            if kind.startswith("nifti") and _nifti_has_nonfinite(path, kind == "nifti-gz"):
                raise UnusableImage(f"{filename}: contains NaN or infinite values")
            with tempfile.TemporaryDirectory(prefix="svrnet-read-") as tmp:
                named = Path(tmp) / f"upload{SUFFIX_BY_KIND[kind]}"
                named.symlink_to(Path(path).resolve())
                vol = from_sitk(_squeeze_4d(sitk.ReadImage(str(named)), filename))
        elif kind == "dicom":
            from service.io.dicom import read_dicom_file

            vol = read_dicom_file(path)
        elif kind == "zip":
            vol = _read_dicom_zip(path, filename)
        else:
            raise UnsupportedFile(f"{filename}: not a NIfTI, NRRD, MHA, DICOM or ZIP file (or truncated)")
    except (UnsupportedFile, UnusableImage):
        raise
    except RuntimeError as exc:  # SimpleITK's errors; their text may contain paths, not patient data
        raise UnsupportedFile(f"{filename}: could not be read as {kind} (corrupt or truncated)") from exc
    return validate(vol, filename)


def _nifti_has_nonfinite(path: Path, compressed: bool) -> bool:
    """Scan the raw float voxels of a NIfTI-1 file (ITK's reader silently replaces NaN)."""
    with (gzip.open(path, "rb") if compressed else open(path, "rb")) as f:
        raw = f.read()
    endian = "<" if int.from_bytes(raw[:4], "little") == 348 else ">"
    if int.from_bytes(raw[:4], "little" if endian == "<" else "big") != 348:
        return False  # NIfTI-2: left to the reader
    datatype = int(np.frombuffer(raw, endian + "i2", 1, 70)[0])
    dtype = {16: "f4", 64: "f8"}.get(datatype)
    if dtype is None:
        return False
    offset = int(np.frombuffer(raw, endian + "f4", 1, 108)[0])
    data = np.frombuffer(raw, endian + dtype, (len(raw) - offset) // np.dtype(dtype).itemsize, offset)
    return not np.isfinite(data).all()


def _squeeze_4d(image: sitk.Image, filename: str) -> sitk.Image:
    if image.GetNumberOfComponentsPerPixel() > 1:
        raise UnusableImage(f"{filename}: 4D or multi-component image ({image.GetNumberOfComponentsPerPixel()} "
                            "values per voxel); upload one 3D stack per file")
    dim = image.GetDimension()
    if dim == 4:
        size = image.GetSize()
        if size[3] != 1:
            raise UnusableImage(f"{filename}: 4D image with {size[3]} volumes; upload one 3D stack per file")
        return sitk.Extract(image, size[:3] + (0,), (0, 0, 0, 0))
    if dim == 2:
        raise UnusableImage(f"{filename}: 2D image; a stack of slices (3D) is required")
    if dim != 3:
        raise UnusableImage(f"{filename}: {dim}D image; a 3D stack is required")
    return image


def validate(vol: Volume, filename: str) -> Volume:
    """Reject volumes the service cannot use."""
    a = vol.array
    if a.ndim != 3:
        raise UnusableImage(f"{filename}: {a.ndim}D image; a 3D stack is required")
    if min(a.shape) < 1 or a.size == 0:
        raise UnusableImage(f"{filename}: empty image (shape {list(a.shape)})")
    if min(a.shape) < 2:
        raise UnusableImage(f"{filename}: 2D image (shape {list(a.shape)}); a stack of at least two slices is required")
    if not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
        raise UnusableImage(f"{filename}: unsupported pixel type {a.dtype}")
    if not np.isfinite(a).all():
        raise UnusableImage(f"{filename}: contains NaN or infinite values")
    if not np.isfinite(vol.affine).all() or abs(np.linalg.det(vol.affine[:3, :3])) < 1e-9:
        raise UnusableImage(f"{filename}: invalid geometry (singular voxel-to-world matrix)")
    return Volume(a.astype(np.float32, copy=False), vol.affine)


def _read_dicom_zip(path: Path, filename: str) -> Volume:
    with tempfile.TemporaryDirectory(prefix="svrnet-zip-") as tmp:
        try:
            with zipfile.ZipFile(path) as z:
                members = [m for m in z.infolist() if not m.is_dir()]
                if len(members) > 5000:
                    raise UnusableImage(f"{filename}: too many files in the archive ({len(members)})")
                for i, m in enumerate(members):  # flat, safe names: never trust archive paths
                    (Path(tmp) / f"{i:05d}.dcm").write_bytes(z.read(m))
        except (zipfile.BadZipFile, OSError, EOFError) as exc:
            raise UnsupportedFile(f"{filename}: corrupt or truncated ZIP archive") from exc
        reader = sitk.ImageSeriesReader()
        series = reader.GetGDCMSeriesIDs(tmp)
        if not series:
            raise UnsupportedFile(f"{filename}: the ZIP archive holds no DICOM series")
        if len(series) > 1:
            raise UnusableImage(f"{filename}: the ZIP archive holds {len(series)} DICOM series; upload one per file")
        files = reader.GetGDCMSeriesFileNames(tmp, series[0])
        if len(files) == 1:
            from service.io.dicom import read_dicom_file

            return read_dicom_file(Path(files[0]))
        reader.SetFileNames(files)
        return from_sitk(reader.Execute())


__all__ = ["read_upload", "sniff", "validate"]
