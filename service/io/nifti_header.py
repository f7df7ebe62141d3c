"""The geometry fields of a NIfTI-1/2 header: which transform places the voxels, read as the standard
says, and copied into the files the service writes on an upload's grid.

A NIfTI file may hold two voxel -> RAS transforms: the *qform* (a rotation as a quaternion, voxel
sizes from ``pixdim``, an offset) and the *sform* (any affine, three rows ``srow_x/y/z``). The
standard, nibabel and FSL place the voxels by the sform whenever ``sform_code > 0``, else by the
qform. ITK prefers the qform when the sform's code is other than 1 and takes voxel sizes from
``pixdim`` even where the sform says otherwise, so the same file would be placed elsewhere by the
service than by the viewer a user checks it in. The reader therefore takes the sform's affine
itself (:func:`sform_affine`), refuses one whose axes are not at right angles (a sheared grid no
slice of an acquisition has), and writes both transforms of the upload, codes included, into the
masks it returns (:func:`copy_transforms`), so that mask and stack overlay in any viewer.

Example:
    >>> import numpy as np
    >>> head = bytearray(348); head[0:4] = (348).to_bytes(4, "little"); head[344:348] = b"n+1\\0"
    >>> head[254:256] = (2).to_bytes(2, "little")                            # sform_code 2
    >>> head[280:328] = np.array([[0, 0, 3, 1], [1.1, 0, 0, 2], [0, 0.9, 0, 3]], "<f4").tobytes()
    >>> t = parse(bytes(head)); t.sform_code, sform_affine(t)[:3].tolist()
    (2, [[0.0, 0.0, 3.0, 1.0], [1.100000023841858, 0.0, 0.0, 2.0], [0.0, 0.8999999761581421, 0.0, 3.0]])
"""

from __future__ import annotations

import gzip
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from service.geometry import frames

# (header size, byte offsets: dim, pixdim, qform_code, sform_code, quatern_b, srow_x; dim, float and code types)
LAYOUTS = {348: dict(dim=40, pixdim=76, qform_code=252, sform_code=254, quatern=256, srow=280, units=123, d="i2",
                     f="f4", code="i2", unit="u1"),
           540: dict(dim=16, pixdim=104, qform_code=344, sform_code=348, quatern=352, srow=400, units=500, d="i8",
                     f="f8", code="i4", unit="i4")}
SPATIAL_UNITS = {1: "metres", 3: "micrometres"}
"""``xyzt_units`` spatial codes other than millimetres (2) or unknown (0): the service reads every
NIfTI distance as millimetres, as nibabel and FSL do."""
QUATERNION_SLACK = 1e-6
"""How far the squares of a qform's ``b, c, d`` may pass 1 (float32 rounding of a turn by 180 degrees)
and still be read as a rotation, with ``a = 0``."""
MAX_SHEAR_COS = frames.MAX_SHEAR_COS
"""Axes of the sform further from right angles than this are a sheared grid (one tolerance with what
the service can write back: :func:`~service.geometry.frames.itk_from_affine`)."""


@dataclass(frozen=True)
class NiftiTransforms:
    """The geometry fields of a NIfTI header, as stored."""

    qform_code: int
    sform_code: int
    pixdim: tuple[float, ...]
    """``pixdim[0:4]``: qfac and the voxel edges."""
    quatern: tuple[float, ...]
    """``quatern_b, c, d, qoffset_x, y, z``."""
    srow: tuple[float, ...]
    """``srow_x, srow_y, srow_z``, row after row (12 values)."""
    axes: int = 3
    """The image's spatial axes (``dim[0]``, 1 to 3)."""
    header_size: int = 348
    """348 for NIfTI-1, 540 for NIfTI-2."""
    spatial_unit: int = 2
    """``xyzt_units & 7``: the unit the header names for distances (2: mm; :data:`SPATIAL_UNITS`)."""


def parse(head: bytes) -> NiftiTransforms | None:
    """The geometry fields of a NIfTI-1 or -2 header (either byte order), or None for another file."""
    for size, at in LAYOUTS.items():
        for endian in "<>":
            if len(head) >= size and int(np.frombuffer(head, endian + "i4", 1, 0)[0]) == size:
                def values(offset: int, count: int, kind: str = at["f"]) -> tuple[float, ...]:
                    return tuple(float(x) for x in np.frombuffer(head, endian + kind, count, offset))
                return NiftiTransforms(int(values(at["qform_code"], 1, at["code"])[0]),
                                       int(values(at["sform_code"], 1, at["code"])[0]),
                                       values(at["pixdim"], 4), values(at["quatern"], 6), values(at["srow"], 12),
                                       int(np.clip(values(at["dim"], 1, at["d"])[0], 1, 3)), size,
                                       int(values(at["units"], 1, at["unit"])[0]) & 7)
    return None


def read_transforms(path: Path) -> NiftiTransforms | None:
    """:func:`parse` of the header of the NIfTI file at ``path`` (``.nii`` or gzipped)."""
    with open(path, "rb") as f:
        gzipped = f.read(2) == b"\x1f\x8b"
    with (gzip.open(path, "rb") if gzipped else open(path, "rb")) as f:
        return parse(f.read(540))


def sform_affine(t: NiftiTransforms) -> NDArray[np.float64]:
    """The sform as a 4 x 4 voxel -> RAS mm matrix."""
    out = np.eye(4)
    out[:3] = np.reshape(t.srow, (3, 4))
    return out


def qform_affine(t: NiftiTransforms) -> NDArray[np.float64]:
    """The qform as a 4 x 4 voxel -> RAS mm matrix, built as nibabel builds it (the standard's
    ``quatern_to_mat44``): the rotation of the quaternion whose ``a`` follows from ``b, c, d``
    (:func:`nibabel.quaternions.fillpositive`, ``a = 0`` within :data:`QUATERNION_SLACK` of a turn by
    180 degrees, as :func:`qform_problem` lets through), the voxel edges ``pixdim[1..3]`` (the third
    times ``qfac``, -1 where ``pixdim[0]`` is negative, else 1) and the offsets, read as millimetres
    whatever ``xyzt_units`` says, as the sform is.

    ITK scales both voxel edges and offsets of the qform by the unit the header names (a thousand
    for metres, a thousandth for microns), which nibabel, FSL and the sform's reading do not: the
    same header would place its voxels a thousand times larger by its qform than by an identical
    sform or through nibabel (a NIfTI-2 file).

    Example:
        >>> t = NiftiTransforms(1, 0, (-1.0, 1.1, 0.9, 3.3), (0.0, 0.0, 1.0, 5.0, -4.0, 2.0), (0.0,) * 12)
        >>> (qform_affine(t).round(6) + 0.0).tolist()
        [[-1.1, 0.0, 0.0, 5.0], [0.0, -0.9, 0.0, -4.0], [0.0, 0.0, -3.3, 2.0], [0.0, 0.0, 0.0, 1.0]]
    """
    qfac = -1.0 if t.pixdim[0] < 0 else 1.0
    out = np.eye(4)
    from nibabel.quaternions import fillpositive, quat2mat   # here: a training host without nibabel imports this module

    rotation = quat2mat(fillpositive(np.asarray(t.quatern[:3], np.float64), QUATERNION_SLACK))
    out[:3, :3] = rotation * np.array([t.pixdim[1], t.pixdim[2], qfac * t.pixdim[3]])
    out[:3, 3] = t.quatern[3:]
    return out


def missing_voxel_size(t: NiftiTransforms) -> str | None:
    """The voxel edges ``pixdim[1..3]`` (as text) where one of the image's axes has none (zero,
    negative or not finite), else None. ITK puts 1 mm in its place without a word, and every pose and
    volume would then be of a grid the file never held; it matters where the qform places the voxels
    (the sform carries its own sizes)."""
    edges = np.asarray(t.pixdim[1:1 + t.axes], np.float64)
    return None if np.all(np.isfinite(edges)) and np.all(edges > 0) else ", ".join(f"{e:g}" for e in edges)


def orientation_problem(t: NiftiTransforms) -> str | None:
    """Why the header does not place the voxels in the scanner (neither ``qform_code`` nor
    ``sform_code`` above 0), or None.

    Without either transform the standard falls back to ``pixdim`` alone along +x, +y, +z, ITK to
    -x, -y, +z and nibabel to -x, +y, +z: three readers, three placements, two of them mirror
    images of the third. Which side of the fetus is left decides the twin a pose is on, so such a
    file has no answer to give.

    Example:
        >>> t = NiftiTransforms(0, 0, (1.0, 1.0, 1.0, 3.0), (0.0,) * 6, (0.0,) * 12)
        >>> orientation_problem(t)[:52]
        'its NIfTI header places its voxels nowhere (qform_co'
    """
    if t.qform_code > 0 or t.sform_code > 0:
        return None
    return ("its NIfTI header places its voxels nowhere (qform_code and sform_code 0): the orientation in "
            "the scanner, and which side is left, are unknown; convert the series again with its geometry "
            "(e.g. dcm2niix)")


def qform_problem(t: NiftiTransforms) -> str | None:
    """Why the qform cannot place the voxels (a quaternion or offset that is not finite, or whose
    ``b, c, d`` are no rotation's: their squares summing over 1), or None. ITK reads such a qform as
    the identity or a zero offset without a word: a placement the file never held.

    Example:
        >>> t = NiftiTransforms(1, 0, (1.0, 1.0, 1.0, 3.0), (0.0, 0.0, float("nan"), 0.0, 0.0, 0.0), (0.0,) * 12)
        >>> qform_problem(t)
        'its NIfTI qform holds values that are not finite'
    """
    quatern = np.asarray(t.quatern, np.float64)
    if not np.all(np.isfinite(quatern)):
        return "its NIfTI qform holds values that are not finite"
    if float(quatern[:3] @ quatern[:3]) > 1.0 + QUATERNION_SLACK:
        return "its NIfTI qform's quaternion (quatern_b, c, d) is no rotation (their squares sum over 1)"
    return None


def sform_problem(t: NiftiTransforms) -> str | None:
    """Why the sform cannot place an acquisition's voxels (not finite, an axis of no length, axes not
    at right angles), or None."""
    axes = sform_affine(t)[:3, :3]
    if not np.all(np.isfinite(axes)):
        return "its NIfTI sform holds values that are not finite"
    if np.linalg.norm(axes, axis=0).min() <= 0:
        return "its NIfTI sform gives an axis no length"
    if (cos := float(frames.axes_cosine(axes))) > MAX_SHEAR_COS:
        return (f"its NIfTI sform is sheared (voxel axes {np.degrees(np.arccos(cos)):.2f} deg apart, not 90); "
                "resample the stack to a grid with axes at right angles")
    return None


ALIGNED_ANAT = 2
"""NIfTI's ``xform_code`` for coordinates aligned to an anatomical reference (here the atlas); 1,
what ITK writes, says the scanner's coordinates, which a volume in atlas space is not."""


RIGID_TOLERANCE = 1e-3
"""How far a map's rotation part may lie from a rotation (largest entry of ``R^T R - I``) and still be one."""


def qform_from_sform(t: NiftiTransforms | None) -> NDArray[np.float64] | None:
    """Where a file's qform places the voxel its sform places at ``p`` (RAS mm -> RAS mm, ``qform ·
    sform^-1``): the move between the two readings of a file whose header sets both transforms
    (codes over 0), which the service reads by the sform and ITK, with a sform code other than 1, by
    the qform. None where the header does not set both, or the two agree, or the move is no rotation
    and shift (a qform could not follow a volume placed by it).

    Example (a qform 15 mm along x from the sform):
        >>> from dataclasses import replace
        >>> t = NiftiTransforms(1, 2, (1.0, 1.0, 1.0, 3.0), (0.0, 0.0, 0.0, 15.0, 0.0, 0.0),
        ...                     (1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 3.0, 0))
        >>> qform_from_sform(t)[:3, 3].tolist(), qform_from_sform(replace(t, qform_code=0))
        ([15.0, 0.0, 0.0], None)
    """
    if t is None or t.qform_code <= 0 or t.sform_code <= 0:
        return None
    move = qform_affine(t) @ np.linalg.inv(sform_affine(t))
    rotation = move[:3, :3]
    if np.abs(rotation.T @ rotation - np.eye(3)).max() > RIGID_TOLERANCE or np.linalg.det(rotation) <= 0:
        return None
    if np.abs(move - np.eye(4)).max() <= RIGID_TOLERANCE:
        return None
    return move


def placed_by(sform: NDArray, qform: NDArray, qform_code: int, sform_code: int,
              spatial_unit: int = 2) -> NiftiTransforms:
    """The header fields (:func:`copy_transforms`) of a NIfTI-1 file placed by ``sform`` and ``qform``
    (voxel -> RAS, each with orthogonal axes) under these codes, qfac and quaternion as the standard
    builds them (nibabel's ``set_qform``), its distance unit ``spatial_unit`` (2: mm; another file's
    unit where the file is to overlay that one in ITK, which scales a qform by it).

    Example:
        >>> a = np.diag([-1.2, 1.2, 3.0, 1.0]); a[:3, 3] = (5.0, -4.0, 2.0)
        >>> t = placed_by(a, a, 1, 2)
        >>> bool(np.allclose(qform_affine(t), a, atol=1e-5)), t.sform_code, t.pixdim[1:]
        (True, 2, (1.2000000476837158, 1.2000000476837158, 3.0))
    """
    import nibabel

    header = nibabel.Nifti1Header()
    header.set_qform(np.asarray(qform, np.float64), int(qform_code))
    header.set_sform(np.asarray(sform, np.float64), int(sform_code))
    quatern = ("quatern_b", "quatern_c", "quatern_d", "qoffset_x", "qoffset_y", "qoffset_z")
    return NiftiTransforms(int(header["qform_code"]), int(header["sform_code"]),
                           tuple(float(v) for v in header["pixdim"][:4]), tuple(float(header[k]) for k in quatern),
                           tuple(float(v) for row in ("srow_x", "srow_y", "srow_z") for v in header[row]),
                           spatial_unit=int(spatial_unit))


def copy_transforms(path: Path, t: NiftiTransforms) -> None:
    """Write ``t`` into the header of the NIfTI-1 file at ``path`` (``.nii`` or ``.nii.gz``, as the
    service writes them): both transforms and their codes, qfac, the voxel edges and the unit they are
    in (ITK scales a qform by it: a mask in millimetres over a stack in metres lies elsewhere in ITK's
    viewers). Nothing else of the upload's header (descriptions, names) is copied."""
    _put_fields(path, {"qform_code": [t.qform_code], "sform_code": [t.sform_code], "pixdim": t.pixdim,
                       "quatern": t.quatern, "srow": t.srow, "units": [t.spatial_unit]})


def set_sform(path: Path, affine: NDArray[np.float64]) -> None:
    """Write ``affine`` (voxel -> RAS mm) as the sform of the NIfTI-1 file at ``path`` (as the service
    writes them), its code unchanged."""
    _put_fields(path, {"srow": tuple(float(v) for v in np.asarray(affine, np.float64)[:3].ravel())})


def set_codes(path: Path, code: int) -> None:
    """Set both ``qform_code`` and ``sform_code`` of the NIfTI-1 file at ``path`` (as the service writes
    them) to ``code``, the transforms themselves unchanged: what their coordinates are
    (:data:`ALIGNED_ANAT` for a volume in atlas space)."""
    _put_fields(path, {"qform_code": [code], "sform_code": [code]})


def _put_fields(path: Path, fields: dict[str, tuple[float, ...] | list[int]]) -> None:
    """Overwrite the named header fields (:data:`LAYOUTS`' names; codes as integers, the rest as
    floats) of the NIfTI-1 file at ``path``, in its byte order, gzipped as it was."""
    compressed = path.name.endswith(".gz")
    data = bytearray(gzip.decompress(path.read_bytes()) if compressed else path.read_bytes())
    endian = "<" if int.from_bytes(data[:4], "little") == 348 else ">"
    at = LAYOUTS[348]
    for name, values in fields.items():
        if name == "units":                             # the spatial bits; the time unit kept as written
            values = [(int(data[at[name]]) & ~7) | (int(values[0]) & 7)]
        kind = at["unit"] if name == "units" else at["code"] if name.endswith("_code") else at["f"]
        raw = np.asarray(values, endian + kind).tobytes()
        data[at[name]:at[name] + len(raw)] = raw
    path.write_bytes(gzip.compress(bytes(data), compresslevel=6) if compressed else bytes(data))
