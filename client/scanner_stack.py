"""Stack files cut into the slices a scanner would send, for ``svrnet stream`` (:mod:`client.stream`).

A stack file is cut along its slice axis (the voxel axis of largest spacing, ties to the last, as
``/v1/predict`` does, :func:`slice_axis_of`) into 2D slices, each with the ``scanner_from_voxel``
a scanner would send it with (:func:`scanner_slices`); :func:`read_stack` does so for a NIfTI file
and its mask.

Example:
    >>> from client.scanner_stack import read_stack
    >>> stack = read_stack("ax.nii.gz", mask_path="ax_mask.nii.gz")                 # doctest: +SKIP
    >>> [s.index for s in stack.slices[:3]]                                           # doctest: +SKIP
    [0, 1, 2]
"""

from __future__ import annotations

import gzip
import logging
import zlib
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import nibabel as nib
import numpy as np
from numpy.typing import NDArray

from client.errors import UnsupportedFile, UnusableInput

__all__ = ["SENT_DTYPES", "ScannerSlice", "ScannerStack", "slice_axis_of", "scanner_slices", "read_stack"]

SENT_DTYPES = ("uint8", "int16", "uint16")   # sent as they are; any other as float32 (all little endian)


@dataclass(frozen=True)
class ScannerSlice:
    """One slice as a scanner sends it.

    Attributes:
        index: its position along the stack's slice axis, 0-based.
        pixels: ``[n0, n1]``: the two in-plane voxel axes of the file, in increasing axis order.
        scanner_from_voxel: ``4 x 4``: voxel ``(i0, i1, 0, 1)`` of ``pixels`` -> scanner RAS mm.
        mask: ``[n0, n1]`` brain mask (``None``: the server finds the brain).
    """

    index: int
    pixels: NDArray
    scanner_from_voxel: NDArray[np.float64]
    mask: NDArray[np.bool_] | None = None


@dataclass(frozen=True)
class ScannerStack:
    """A stack file cut into the slices a scanner would send: its ``name`` in the session, the file's
    ``slice_axis`` and its ``slices`` in index order."""

    name: str
    slice_axis: int
    slices: list[ScannerSlice]


SPACING_TIE = 1e-3
"""Spacings within this share of the largest tie (the server's ``SPACING_TIE``): a header's rounding
(3.0 and 2.9995 mm) does not choose the slice axis."""


def slice_axis_of(spacing: Sequence[float]) -> int:
    """The voxel axis of largest spacing; ties (within :data:`SPACING_TIE`) go to the last axis (as
    the server's ``/v1/predict``).

    Example:
        >>> slice_axis_of([1.0, 4.0, 1.0]), slice_axis_of([3.0, 1.0, 3.0]), slice_axis_of([2.0, 2.0, 2.0])
        (1, 2, 2)
        >>> slice_axis_of([3.0, 1.0, 2.9995])
        2
    """
    sp = np.asarray(spacing, dtype=np.float64)
    return int(np.flatnonzero(sp >= sp.max() * (1 - SPACING_TIE))[-1])


def scanner_slices(image: NDArray, affine: NDArray, mask: NDArray | None = None) -> tuple[int, list[ScannerSlice]]:
    """The slices a scanner would send of a 3D ``image`` with its voxel -> RAS mm ``affine``.

    Args:
        image: the stack's voxels ``[n_x, n_y, n_z]``.
        affine: ``4 x 4``, voxel -> RAS mm (a NIfTI file's affine).
        mask: brain mask on the image's grid, or ``None``.

    Returns:
        The slice axis and the slices in index order: voxel ``(i0, i1, 0)`` of slice ``k`` is voxel
        ``(k, i0, i1)``, ``(i0, k, i1)`` or ``(i0, i1, k)`` of ``image`` as the slice axis is 0, 1 or 2.

    Example:
        >>> affine = np.diag([1.0, 4.0, 1.5, 1.0])                 # axis 1 is the thickest: the slice axis
        >>> axis, slices = scanner_slices(np.arange(24).reshape(2, 3, 4), affine)
        >>> axis, len(slices), slices[2].pixels.shape, int(slices[2].pixels[1, 3])
        (1, 3, (2, 4), 23)
        >>> slices[2].scanner_from_voxel @ [1, 3, 0, 1]             # voxel (1, 2, 3) of the file
        array([1. , 8. , 4.5, 1. ])
    """
    affine = np.asarray(affine, dtype=np.float64)
    axis = slice_axis_of(np.linalg.norm(affine[:3, :3], axis=0))
    first, second = (ax for ax in range(3) if ax != axis)
    reordered = affine[:, [first, second, axis, 3]]
    slices = []
    for k in range(image.shape[axis]):
        at = (slice(None),) * axis + (k,)
        scanner_from_voxel = reordered.copy()
        scanner_from_voxel[:3, 3] = affine[:3, 3] + k * affine[:3, axis]
        slices.append(ScannerSlice(k, image[at], scanner_from_voxel, None if mask is None else mask[at] > 0))
    return axis, slices


@contextmanager
def _quiet_nibabel() -> Iterator[None]:
    """nibabel's header notes held back (its logger at ERROR for the while)."""
    logger = logging.getLogger("nibabel.global")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


def is_gzipped(path: Path) -> bool:
    """Whether the file ``path`` is gzip-compressed, by its content (its first two bytes)."""
    with open(path, "rb") as f:
        return f.read(2) == b"\x1f\x8b"


def named_as_stored(path: Path) -> bool:
    """Whether the name of the file ``path`` says its compression (``.gz`` where gzipped, else not):
    as ITK's readers take it, which go by the name."""
    return is_gzipped(path) == path.name.endswith(".gz")


def nifti_image(path: Path) -> nib.Nifti1Image:
    """The NIfTI image of ``path``, read by its content where its name says gzip and it is not, or the
    reverse (as the server reads it): a plain NIfTI-1 or -2 file named ``.nii.gz``, a gzipped one
    named ``.nii``. nibabel's notes on the header it mends as it reads (``pixdim`` of zero where the
    sform places the voxels) stay out of the command's output: the server reads the file by its own
    rules and says what it refuses."""
    gzipped = is_gzipped(path)
    with _quiet_nibabel():
        if gzipped != path.name.endswith(".gz"):             # the name says the other: read by the content
            raw = gzip.decompress(path.read_bytes()) if gzipped else path.read_bytes()
            nifti2 = 540 in (int.from_bytes(raw[:4], "little"), int.from_bytes(raw[:4], "big"))
            return (nib.Nifti2Image if nifti2 else nib.Nifti1Image).from_bytes(raw)
        return nib.load(str(path))


def _volume(path: Path, what: str) -> tuple[NDArray, NDArray[np.float64]]:
    """A 3D NIfTI file's voxels (scaled where the file says) and its affine."""
    try:
        img = nifti_image(path)
        data = np.asanyarray(img.dataobj)
    except nib.filebasedimages.ImageFileError as e:
        raise UnsupportedFile(f"{what}: {path.name} is not a NIfTI file nibabel can read ({e})") from None
    except (FileNotFoundError, IsADirectoryError, PermissionError):    # the path, not the file's content
        raise
    except (EOFError, OSError, ValueError, zlib.error) as e:          # a truncated or corrupt file
        raise UnsupportedFile(f"{what}: {path.name} is truncated or corrupt ({type(e).__name__}: {e})") from None
    stored = img.get_data_dtype()
    if stored.names is not None or stored.kind not in "iuf":           # RGB, complex: as the server refuses them
        raise UnusableInput(f"{what}: {path.name}: unsupported pixel type {stored} (one real number per voxel "
                            "is required)")
    data = data.reshape(data.shape[:3]) if data.ndim > 3 and np.prod(data.shape[3:]) == 1 else data
    if data.ndim != 3:
        raise UnusableInput(f"{what}: {path.name} has shape {data.shape}; a stack is 3D")
    if all(int(img.header.get(code, 0)) <= 0 for code in ("qform_code", "sform_code")):
        # readers disagree where such a file's voxels lie (mirror images of one another): the server refuses it too
        raise UnusableInput(f"{what}: {path.name}: its NIfTI header places its voxels nowhere (qform_code and "
                            "sform_code 0); convert the series again with its geometry (e.g. dcm2niix)")
    return data, np.asarray(img.affine, dtype=np.float64)


def mask_voxels(array: NDArray) -> NDArray[np.bool_]:
    """The voxels a mask file marks, by the server's rule for an uploaded mask (its
    ``service.pipeline.stack_upload.mask_voxels``; this client installs without the server): every nonzero
    voxel of a mask of whole numbers (a mask of 255 saved as signed bytes marks its brain by -1), and
    of a mask of fractions (a probability map) those at half its largest magnitude or more.

    Example:
        >>> mask_voxels(np.array([0, -1, 1], np.int8)).tolist(), mask_voxels(np.array([0.02, 0.3, 0.9])).tolist()
        ([False, True, True], [False, False, True])
    """
    a = np.asarray(array)
    if a.dtype.kind in "biu":
        return a != 0
    a = np.where(np.isfinite(a), a, 0.0)
    if not a.size or np.array_equal(a, np.round(a)):
        return a != 0
    return np.abs(a) >= 0.5 * float(np.abs(a).max())


def in_stack_order(mask: NDArray, mask_affine: NDArray, stack_affine: NDArray) -> tuple[NDArray, NDArray]:
    """A mask's voxels and affine brought into its stack's axis order and directions (nibabel's
    orientation tools), as the server takes a mask file that stores its stack's voxels in another
    order; a mask on another grid keeps a grid that then differs from the stack's.

    Example (the mask's first axis stored the other way, its affine saying so):
        >>> stack = np.diag([1.0, 1.0, 3.0, 1.0])
        >>> m = np.zeros((3, 2, 2), np.uint8); m[0] = 1
        >>> flipped = stack @ np.array([[-1.0, 0, 0, 2], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
        >>> out, affine = in_stack_order(m[::-1], flipped, stack)
        >>> out[:, 0, 0].tolist(), bool(np.allclose(affine, stack))
        ([1, 0, 0], True)
    """
    ornt = nib.orientations.ornt_transform(nib.orientations.io_orientation(mask_affine),
                                           nib.orientations.io_orientation(stack_affine))
    affine = mask_affine @ nib.orientations.inv_ornt_aff(ornt, mask.shape)
    return np.ascontiguousarray(nib.orientations.apply_orientation(mask, ornt)), affine


def read_stack(path: str | Path, mask_path: str | Path | None = None, name: str | None = None) -> ScannerStack:
    """A NIfTI stack file (and its mask on the same grid) cut into the slices a scanner would send.

    Pixels of ``uint8``, ``int16`` or ``uint16`` files go out as they are; any other type as ``float32``.

    Args:
        path: the stack file (``.nii`` or ``.nii.gz``).
        mask_path: its brain mask on the same grid (its voxels in any axis order:
            :func:`in_stack_order`), or ``None`` (the server finds the brain).
        name: the stack's name in the session (default: the file name without its extension).

    Raises:
        UnsupportedFile: a file nibabel cannot read. UnusableInput: not 3D, or the mask's grid differs.
    """
    path = Path(path)
    image, affine = _volume(path, "stack")
    if image.dtype.name not in SENT_DTYPES:
        image = image.astype(np.float32)
    mask = None
    if mask_path is not None:
        stored, stored_affine = _volume(Path(mask_path), "mask")
        mask, mask_affine = in_stack_order(mask_voxels(stored), stored_affine, affine)
        if mask.shape != image.shape or not np.allclose(mask_affine, affine, atol=1e-3):
            why = (f"shape {list(stored.shape)} against {list(image.shape)}" if mask.shape != image.shape else
                   "the same shape at another origin, spacing or orientation")
            raise UnusableInput(f"mask: {Path(mask_path).name} is not on the grid of its stack {path.name} ({why})")
    axis, slices = scanner_slices(image, affine, mask)
    return ScannerStack(name or path.name.removesuffix(".gz").removesuffix(".nii"), axis, slices)
