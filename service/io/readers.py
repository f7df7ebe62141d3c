"""Uploaded files -> :class:`Volume`, recognised by content (magic bytes), not by file name.

Formats: NIfTI-1 and -2 (``.nii``, ``.nii.gz``; NIfTI-2 through nibabel), NRRD, MetaImage
(``.mha``), a single DICOM file (classic, Enhanced multi-frame, or Siemens mosaic), or a ``.zip``
holding one DICOM series. DICOM files are de-identified on read: only pixel data and geometry leave
this module, no tag values are logged.

Validation (each failure raises with the file's name, never a tag value):
* unreadable, truncated, unknown or inconsistent (any parser error) -> :class:`UnsupportedFile` (415);
* NRRD / MetaImage headers that point at a detached data file, however long the header, and NIfTI
  ``.hdr/.img`` pairs -> 415: a header must never make the server open a path. Readers only ever see
  the upload's bytes, behind a header rebuilt from allowed fields (:mod:`service.io.headers`), through
  the ImageIO chosen by the sniffed content;
* data that decode to more than the file's or the request's budget (gzip, ZIP or DICOM bombs, many
  files at once) -> :class:`PayloadTooLarge` (413), charged while inflating and before any voxel
  array is allocated (:mod:`service.io.limits`);
* 2D, 4D with more than one volume, empty, or non-finite values, a NIfTI header without voxel
  sizes, a grid no MRI acquisition has (:mod:`service.io.acquisition_geometry`) -> :class:`UnusableImage` (422).
"""

from __future__ import annotations

import gzip
import tempfile
import zlib
from dataclasses import replace
from pathlib import Path

import nibabel
import numpy as np
import SimpleITK as sitk
from isal import igzip, isal_zlib

from service.core.errors import ServiceError, UnsupportedFile, UnusableImage
from service.geometry import frames
from service.io.acquisition_geometry import grid_problem, slice_axis_problem, stacking_problem
from service.io.archive import read_dicom_zip
from service.io.dicom import read_dicom_file
from service.io.bare_dicom import as_part10, bare_dicom
from service.io.header_geometry import geometry_problem
from service.io.headers import clean_header, declared_grid
from service.io.limits import DecodeBudget, FileBudget, raise_if_out_of_space
from service.io.nifti_header import (MAX_SHEAR_COS, SPATIAL_UNITS, NiftiTransforms, missing_voxel_size,
                                     orientation_problem, qform_problem, read_transforms, sform_problem)
from service.io.volume import SITK_FILES, Volume, from_sitk, magnitude, placed_by_header

SUFFIX_BY_KIND = {"nifti": ".nii", "nifti-gz": ".nii.gz", "nrrd": ".nrrd", "mha": ".mha"}
MAX_DECODED_BYTES = 128 * 2**20
IMAGE_IO = {"nifti": "NiftiImageIO", "nrrd": "NrrdImageIO", "mha": "MetaImageIO"}
GZIP_ERRORS = (OSError, EOFError, zlib.error, isal_zlib.error)
"""What a truncated, corrupt or non-gzip stream raises while it is inflated."""

sitk.ProcessObject_SetGlobalWarningDisplay(False)   # ITK's warnings reach stderr as plain text naming the file read


def sniff(path: Path) -> str:
    """The kind of file: ``nifti``, ``nifti-gz``, ``nrrd``, ``mha``, ``dicom``, ``zip``, ``bare-dicom``
    (a DICOM data set without the file preamble, :func:`~service.io.bare_dicom.bare_dicom`) or ``unknown``
    (from the first bytes; a gzip stream's integrity is checked when it is decoded, once)."""
    with open(path, "rb") as f:
        head = f.read(1024)
    if head[:2] == b"\x1f\x8b":
        try:
            with gzip.open(path, "rb") as g:   # the first bytes of a stream even when it is truncated
                inner = g.read(352)
        except GZIP_ERRORS:
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
    if head[:4] in (b"PK\x03\x04", b"PK\x05\x06"):       # a ZIP, or an empty one
        return "zip"
    if bare_dicom(head):
        return "bare-dicom"
    return "unknown"


def _read_dicom(path: Path, filename: str, kind: str, budget: FileBudget, scratch: Path | None) -> Volume:
    """One DICOM file; a bare data set (``kind`` ``bare-dicom``) read from its copy as a DICOM file."""
    if kind == "dicom":
        return read_dicom_file(path, filename, budget)
    with tempfile.TemporaryDirectory(prefix="svrnet-read-", dir=scratch) as tmp:
        try:
            as_part10(path, Path(tmp) / "upload.dcm", filename)
        except OSError as exc:
            raise_if_out_of_space(exc)            # a full disk is the server's (507), not the file's
            raise
        return read_dicom_file(Path(tmp) / "upload.dcm", filename, budget)


def _is_nifti(head: bytes) -> bool:
    if len(head) < 348:
        return False
    sizeof = int.from_bytes(head[:4], "little"), int.from_bytes(head[:4], "big")
    return (348 in sizeof and head[344:348] in (b"n+1\x00", b"ni1\x00")) or 540 in sizeof


def read_upload(path: Path, filename: str, max_decoded_bytes: int = MAX_DECODED_BYTES,
                budget: FileBudget | None = None, scratch: Path | None = None, magnitudes: bool = True) -> Volume:
    """Read one uploaded file as a 3D :class:`Volume`; ``filename`` is used in error messages only.

    ``budget`` (default: ``max_decoded_bytes`` for this file alone) is charged by every decoder as it
    decodes: gzip, ZIP members, DICOM deflate and the voxel array itself (see :mod:`service.io.limits`).
    ``scratch``: where the decoded copies go while the file is read (a ZIP's members, a gunzipped
    NIfTI; default: the system's temporary folder). The service passes the folder of the request or
    job the upload belongs to, so that a process killed while reading leaves them where that
    request's or job's own clean-up removes them. ``magnitudes``: the values read as an image's
    magnitudes (:func:`validate`); False for a mask, whose labels keep their values (a mask saved as
    signed numbers marks its brain by -1 as well as by 1).
    Whatever a parser raises on a client's bytes becomes a 4xx naming ``filename``, never a 500.
    """
    budget = budget or DecodeBudget(max_decoded_bytes).file(filename)
    try:
        kind = sniff(path)
        if kind in SUFFIX_BY_KIND:
            with tempfile.TemporaryDirectory(prefix="svrnet-read-", dir=scratch) as tmp:
                if kind == "nifti-gz":   # decoded once, here; the checks and SimpleITK read the plain file
                    path, kind = _gunzip(path, Path(tmp) / "decoded.nii", budget), "nifti"
                if kind == "nifti" and _nifti_pair(path):
                    raise UnsupportedFile(f"{filename}: the header of a NIfTI .hdr/.img pair (its voxels are in "
                                          "another file); upload a single .nii or .nii.gz")
                if kind == "nifti" and (problem := _nifti1_problem(path)) is not None:
                    raise UnsupportedFile(f"{filename}: {problem}")
                if kind == "nifti" and _nifti_has_nonfinite(path):
                    raise UnusableImage(f"{filename}: contains NaN or infinite values")
                transforms = read_transforms(path) if kind == "nifti" else None
                if transforms is not None and (problem := orientation_problem(transforms)) is not None:
                    raise UnusableImage(f"{filename}: {problem}")
                by_sform = transforms is not None and transforms.sform_code > 0
                if by_sform and (problem := sform_problem(transforms)) is not None:
                    raise UnusableImage(f"{filename}: {problem}")
                if transforms is not None and not by_sform and (problem := qform_problem(transforms)) is not None:
                    raise UnusableImage(f"{filename}: {problem}")
                if transforms is not None and not by_sform and (pixdim := missing_voxel_size(transforms)) is not None:
                    raise UnusableImage(f"{filename}: its NIfTI header gives no voxel size (pixdim[1:4] = {pixdim}); "
                                        "the reader would invent 1 mm")
                # SimpleITK reads a copy named by the sniffed content, with the reader chosen here
                # (never by probing), and for NRRD/MHA a header rebuilt from allowed fields.
                named = Path(tmp) / f"upload{SUFFIX_BY_KIND[kind]}"
                header = None
                if kind in ("nrrd", "mha"):
                    with open(path, "rb") as src, open(named, "wb") as dst:
                        header = clean_header(src, dst, kind, filename, budget.limit)
                else:
                    named.symlink_to(Path(path).resolve())
                if transforms is not None and transforms.header_size == 540:      # NIfTI-2
                    vol = _read_by_nibabel(named, filename, budget, transforms)
                else:
                    charged = False
                    try:
                        sizes, channels = _declared_grid(named, kind) if header is None \
                            else declared_grid(header, kind, filename)
                        budget.voxels(int(np.prod(sizes, dtype=object)) * channels)
                        budget.grid(sizes)
                        charged = True
                        with SITK_FILES:
                            image = _reader(named, kind).Execute()
                    except RuntimeError as exc:
                        if not (by_sform and "orthonormal" in str(exc)):
                            raise
                        # ITK refuses an sform whose axes are a hair off right angles (as converters'
                        # float32 rounding leaves them); the sform is read here, the voxels by nibabel.
                        vol = _read_by_nibabel(named, filename, budget, transforms, charged)
                    else:
                        vol = placed_by_header(from_sitk(_squeeze_4d(image, filename)), transforms)
                    if header is not None and (problem := geometry_problem(header, kind)) is not None:
                        raise UnusableImage(f"{filename}: {problem}")      # what the reader made up
        elif kind in ("dicom", "bare-dicom", "zip"):
            vol = read_dicom_zip(path, filename, budget, scratch) if kind == "zip" else _read_dicom(path, filename, kind,
                                                                                                    budget, scratch)
            if (problem := stacking_problem(vol.spacing, vol.array.shape[2])) is not None:
                raise UnusableImage(f"{filename}: {problem}")
        else:
            raise UnsupportedFile(f"{filename}: not a NIfTI, NRRD, MHA, DICOM or ZIP file (or truncated)")
    except ServiceError:
        raise
    except MemoryError:
        raise
    except Exception as exc:  # noqa: BLE001 - SimpleITK's RuntimeError, pydicom's and numpy's errors ...
        # The text may hold paths or tag values: it stays out of the answer and the log.
        raise UnsupportedFile(f"{filename}: could not be read (corrupt, truncated or inconsistent file)") from exc
    checked = validate(vol, filename, magnitudes)
    if kind in SUFFIX_BY_KIND and (problem := slice_axis_problem(checked.spacing)) is not None:
        raise UnusableImage(f"{filename}: {problem}")          # a DICOM stack's third axis is its slices'
    return checked


def _gunzip(path: Path, out: Path, budget: FileBudget) -> Path:
    """Decode a gzip file to ``out``, charging ``budget`` as it inflates (a NIfTI header that declares
    too much is refused before anything else is inflated); truncated or corrupt streams are 415.

    ISA-L's inflate (``isal.igzip``, the ``gzip`` module's interface) decodes faster than
    zlib's, a share of every request that uploads ``.nii.gz``."""
    try:
        with igzip.open(path, "rb") as src, open(out, "wb") as dst:
            head = src.read(352)
            dims = _nifti_dims(head)
            if (declared := _nifti_values(dims)) * 4 > budget.limit:
                raise budget.declared_too_large(declared)
            budget.grid(dims)
            budget.inflate(len(head))
            dst.write(head)
            while chunk := src.read(1 << 22):   # to the end: a truncated stream or a bad CRC raises here
                budget.inflate(len(chunk))
                dst.write(chunk)
    except GZIP_ERRORS as exc:
        raise_if_out_of_space(exc)
        raise UnsupportedFile(f"{budget.filename}: truncated or corrupt gzip stream") from exc
    return out


def _nifti_dims(head: bytes) -> list[int]:
    """The axes' sizes a NIfTI-1 or NIfTI-2 header declares, each at least 1 (``[0]`` when it is neither).

    Example:
        >>> head = (348).to_bytes(4, "little") + bytes(36) + np.array([3, 64, 48, 20, 1, 1, 1, 1], "<i2").tobytes()
        >>> _nifti_dims(head + bytes(300)), _nifti_dims(bytes(352))
        ([64, 48, 20], [0])
    """
    sizes = int.from_bytes(head[:4], "little"), int.from_bytes(head[:4], "big")
    for size, offset, kind in ((348, 40, "i2"), (540, 16, "i8")):
        if len(head) >= offset + 64 and size in sizes:
            endian = "<" if sizes[0] == size else ">"
            dim = np.frombuffer(head, endian + kind, 8, offset).astype(np.float64)
            return [int(min(n, 2.0 ** 62)) for n in np.clip(dim[1:1 + int(np.clip(dim[0], 1, 7))], 1, None)]
    return [0]


def _nifti_values(dims: list[int]) -> int:
    """Voxel values of a header's axes' sizes (:func:`_nifti_dims`; 0 when it is no NIfTI header)."""
    return int(min(np.prod(dims, dtype=np.float64), 2.0 ** 62))


def _reader(path: Path, kind: str) -> sitk.ImageFileReader:
    """A SimpleITK reader of ``path`` with the ImageIO of ``kind`` (no other reader is ever tried)."""
    reader = sitk.ImageFileReader()
    reader.SetImageIO(IMAGE_IO[kind])
    reader.SetFileName(str(path))
    return reader


def _declared_grid(path: Path, kind: str) -> tuple[list[int], int]:
    """The axes' sizes and the values per voxel the header declares (read without decoding any voxels)."""
    reader = _reader(path, kind)
    with SITK_FILES:
        reader.ReadImageInformation()
    return [int(n) for n in reader.GetSize()], int(reader.GetNumberOfComponents())


def _nifti_pair(path: Path) -> bool:
    """A NIfTI-1/2 header whose magic says the voxels are in a separate ``.img`` file."""
    with open(path, "rb") as f:
        head = f.read(348)
    return head[344:348] == b"ni1\x00" or head[4:8] == b"ni2\x00"


NIFTI_ITEM_BYTES = {2: 1, 4: 2, 8: 4, 16: 4, 32: 8, 64: 8, 128: 3, 256: 1, 512: 2, 768: 4, 1024: 8, 1280: 8,
                    1536: 16, 1792: 16, 2048: 32, 2304: 4}
"""Bytes of one voxel value by NIfTI ``datatype`` code (what ITK reads the voxels by)."""


def _nifti1_problem(path: Path) -> str | None:
    """What makes an uncompressed single-file NIfTI-1 header impossible to read as it claims, where
    ITK would read it without a word: a data offset inside the 352-byte header (or not a number),
    which shifts every voxel by the header's last bytes; a ``bitpix`` that is not its ``datatype``'s
    (ITK sizes the voxels by ``datatype``); less voxel data than the header declares (ITK fills the
    missing voxels). None for a header with none of these, and for NIfTI-2, which nibabel checks."""
    with open(path, "rb") as f:
        head = f.read(352)
    values = _nifti_values(_nifti_dims(head))
    if not values or 348 not in (int.from_bytes(head[:4], "little"), int.from_bytes(head[:4], "big")):
        return None
    endian = "<" if int.from_bytes(head[:4], "little") == 348 else ">"
    datatype = int(np.frombuffer(head, endian + "i2", 1, 70)[0])
    bitpix = int(np.frombuffer(head, endian + "i2", 1, 72)[0])
    offset = float(np.frombuffer(head, endian + "f4", 1, 108)[0])
    item = NIFTI_ITEM_BYTES.get(datatype)
    if item is None:
        return None                                 # a type the reader refuses itself
    if bitpix != 8 * item:
        return f"inconsistent NIfTI header (bitpix {bitpix} for datatype {datatype}, which has {8 * item})"
    if not (np.isfinite(offset) and offset >= 352):
        return "impossible NIfTI header (its voxel data would start inside the header: vox_offset < 352)"
    if (held := path.stat().st_size - int(offset)) < values * item:
        return (f"truncated NIfTI file (its header declares {values:,} voxels, {values * item:,} bytes of voxel data; "
                f"the file holds {max(held, 0):,})")
    return None


def _nifti_has_nonfinite(path: Path) -> bool:
    """Scan the raw float voxels of an uncompressed NIfTI-1 file (ITK's reader silently replaces NaN)."""
    with open(path, "rb") as f:
        head = f.read(348)
    size = path.stat().st_size
    endian = "<" if int.from_bytes(head[:4], "little") == 348 else ">"
    if int.from_bytes(head[:4], "little" if endian == "<" else "big") != 348:
        return False  # NIfTI-2: left to the reader
    datatype = int(np.frombuffer(head, endian + "i2", 1, 70)[0])
    dtype = {16: "f4", 64: "f8"}.get(datatype)
    if dtype is None:
        return False
    offset = float(np.frombuffer(head, endian + "f4", 1, 108)[0])
    if not np.isfinite(offset) or not 348 <= offset < size:
        return False  # an impossible header: the reader reports it
    count = (size - int(offset)) // np.dtype(dtype).itemsize
    data = np.memmap(path, endian + dtype, mode="r", offset=int(offset), shape=(count,))
    return not np.isfinite(data).all()


def _read_by_nibabel(path: Path, filename: str, budget: FileBudget, transforms: NiftiTransforms,
                     charged: bool = False) -> Volume:
    """A NIfTI file with nibabel: a NIfTI-2 file (which SimpleITK does not read), or a NIfTI-1 file
    whose sform SimpleITK refuses as not orthonormal though it lies within the service's own
    tolerance (:func:`~service.io.nifti_header.sform_problem`). Its declared voxels are charged to
    ``budget`` before any is read (unless ``charged`` already); one 3D volume of real numbers,
    placed as SimpleITK's reading is (:func:`placed_by_header`: the sform when its code is above
    0, else the qform). The voxels are scaled in float32, the only array beside the file's own."""
    nifti2 = transforms.header_size == 540
    image = (nibabel.Nifti2Image if nifti2 else nibabel.Nifti1Image).from_filename(str(path))
    first = 544 if nifti2 else 352                         # one file: the data after header and extension flag
    if image.dataobj.offset < first:
        raise UnsupportedFile(f"{filename}: impossible NIfTI-{2 if nifti2 else 1} header (its voxel data would start "
                              f"inside the header: vox_offset < {first})")          # as a NIfTI-1 header's (415)
    shape = tuple(int(n) for n in image.shape)
    if not charged:
        budget.voxels(int(np.prod(shape, dtype=np.float64)))
    budget.grid(shape)
    if len(shape) < 3:
        raise UnusableImage(f"{filename}: {len(shape)}D image; a stack of slices (3D) is required")
    if any(n != 1 for n in shape[3:]):
        raise UnusableImage(f"{filename}: {len(shape)}D image with {int(np.prod(shape[3:]))} volumes; "
                            "upload one 3D stack per file")
    stored = image.get_data_dtype()
    if stored.names is not None or stored.kind not in "iuf":
        raise UnusableImage(f"{filename}: unsupported pixel type {stored} (one real number per voxel is required)")
    array = np.asarray(image.dataobj.get_unscaled(), dtype=np.float32).reshape(shape[:3])
    slope, inter = image.dataobj.slope, image.dataobj.inter
    if slope != 1.0:
        array *= np.float32(slope)
    if inter != 0.0:
        array += np.float32(inter)
    return placed_by_header(Volume(array, np.asarray(image.affine, np.float64)), transforms)


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


def validate(vol: Volume, filename: str, magnitudes: bool = True) -> Volume:
    """Reject volumes the service cannot use; the values of the others as float32, with ``magnitudes``
    as magnitudes (:func:`~service.io.volume.magnitude`: a file stored with an offset gets its
    background at 0)."""
    a = vol.array
    if a.ndim != 3:
        raise UnusableImage(f"{filename}: {a.ndim}D image; a 3D stack is required")
    if min(a.shape) < 1 or a.size == 0:
        raise UnusableImage(f"{filename}: empty image (shape {list(a.shape)})")
    if min(a.shape) < 2:
        raise UnusableImage(f"{filename}: 2D image (shape {list(a.shape)}); a stack of at least two slices is required")
    if not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
        raise UnusableImage(f"{filename}: unsupported pixel type {a.dtype}")
    a = a.astype(np.float32, copy=False)                # values beyond float32's range become inf here
    if not np.isfinite(a).all():
        raise UnusableImage(f"{filename}: contains NaN or infinite values (or values beyond float32's range)")
    if not np.isfinite(vol.affine).all() or abs(np.linalg.det(vol.affine[:3, :3])) < 1e-9:
        raise UnusableImage(f"{filename}: invalid geometry (singular voxel-to-world matrix)")
    if (problem := grid_problem(vol.affine, a.shape)) is not None:     # first: a voxel of 1e300 mm is no shear
        unit = SPATIAL_UNITS.get(vol.nifti.spatial_unit) if vol.nifti is not None else None
        raise UnusableImage(f"{filename}: {problem}" + (f" (its NIfTI header says its distances are in {unit}; they "
                                                         "are read as millimetres, as nibabel and FSL read them)"
                                                         if unit else ""))
    if (cos := float(frames.axes_cosine(vol.affine[:3, :3]))) > MAX_SHEAR_COS:
        raise UnusableImage(f"{filename}: its voxel axes are sheared ({np.degrees(np.arccos(cos)):.2f} deg apart, "
                            "not 90); resample the stack to a grid with axes at right angles")
    return replace(vol, array=magnitude(a) if magnitudes else a)


__all__ = ["read_upload", "sniff", "validate"]
