"""A volume in the project's convention, and reading/writing it through SimpleITK.

SimpleITK is imported where a file is read or written, so the volume itself (and the training
simulation that uses it) runs on a host without SimpleITK, such as a bare GPU machine.

Arrays are indexed ``[i, j, k]`` (NIfTI voxel order, x fastest on disk); the affine maps voxel
indices to world RAS mm. SimpleITK's ``[k, j, i]`` array order and LPS frame are converted here and
in :mod:`service.geometry.frames`, nowhere else.

Example:
    >>> import numpy as np, tempfile, os
    >>> aff = np.diag([-0.8, 0.8, 3.0, 1.0]); aff[:3, 3] = (10, -20, 5)
    >>> v = Volume(np.zeros((4, 5, 6), np.float32), aff)
    >>> path = os.path.join(tempfile.mkdtemp(), "v.nii.gz"); write_volume(v, path)
    >>> w = read_volume(path); w.array.shape, bool(np.allclose(w.affine, aff))
    ((4, 5, 6), True)
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from service.geometry import frames
from service.io.nifti_header import NiftiTransforms, qform_affine, read_transforms, set_sform, sform_affine

if TYPE_CHECKING:
    import SimpleITK as sitk

SITK_FILES = threading.Lock()
"""Held by every read and write of a file through SimpleITK (its image readers and writers, GDCM's
series lookups): two run at once in one process can crash it inside ITK (a server reading two
uploads at once died of a segmentation fault there). An upload is already decoded when it is read
(gzip is inflated before, :mod:`service.io.readers`); the service's own ``.nii.gz`` files (a job's
volume, a mask) are compressed or inflated under the lock, one at a time, which costs little beside
their jobs. Arrays and filters need no lock."""


@dataclass
class Volume:
    """A 3D image: ``array`` ``[i, j, k]`` and its voxel -> RAS mm ``affine`` (4 x 4)."""

    array: NDArray
    affine: NDArray[np.float64]
    acquisition_order: tuple[int, ...] | None = None
    """The indices ``k`` in the order the scanner acquired the slices, where the file says (a DICOM
    series' per-slice acquisition times; only their order is kept, never the times)."""
    slice_thickness_mm: float | None = None
    """The slices' thickness where the file states it (DICOM ``SliceThickness``) or the client gave it;
    None: unknown, and the slice spacing stands in for it (the reconstruction's slice profile)."""
    slice_axis: int | None = None
    """The axis the slices were acquired along where it is known (a streamed stack, whose slices may
    lie closer together than its pixels); None: the axis of largest spacing."""
    nifti: NiftiTransforms | None = None
    """The transforms of the NIfTI header the volume was read from (None for other files): written
    again into what the service returns on this grid, so that it overlays the upload in any viewer."""

    @property
    def spacing(self) -> NDArray[np.float64]:
        """Voxel sizes along ``i, j, k`` (mm)."""
        return frames.voxel_spacing(self.affine)

    def region(self, box: tuple[slice, slice, slice]) -> "Volume":
        """The voxels of ``box`` (unit-step slices) where they lie: the affine's origin moves to the
        box's first voxel.

        Example:
            >>> v = Volume(np.arange(24.0).reshape(2, 3, 4), np.diag([2.0, 3.0, 4.0, 1.0]))
            >>> r = v.region((slice(1, 2), slice(0, 3), slice(2, 4)))
            >>> r.array.shape, r.affine[:3, 3].tolist()
            ((1, 3, 2), [2.0, 0.0, 8.0])
        """
        affine = np.array(self.affine, dtype=np.float64)
        affine[:3, 3] += affine[:3, :3] @ [b.start or 0 for b in box]
        return Volume(np.asarray(self.array)[box], affine, slice_thickness_mm=self.slice_thickness_mm,
                      slice_axis=self.slice_axis)


BACKGROUND_PERCENTILE = 0.5
"""The share (%) of an image's values, its darkest, taken for the background where it lies below zero."""
MAX_SAMPLED_VALUES = 1 << 20
"""The values :func:`magnitude` takes its background level from at most (a stride over the array)."""
FILL_SHARE, FILL_GAP = 1e-3, 0.5
"""A value below zero is a fill (the padding a tool writes where a resampled or oblique grid has no
data, -1024 or -32768) where at least :data:`FILL_SHARE` of the values hold it, its lowest, and the
next lowest value lies above it by more than :data:`FILL_GAP` of the other values' range."""
FLOOR_SHARE = 0.01
"""An image whose lowest value lies above zero and holds at least this share of its values has its
air stored with an offset (zero-filled air lifted by an added constant or a rescale intercept: the
real scans hold 4-16 % of their values at exactly 0); a noise floor never holds one value that often."""


def air_floor(values: NDArray) -> float:
    """The lowest value of an image without values below zero where it is a floor, :data:`FLOOR_SHARE`
    of the values or more (air stored with an offset), else 0.

    Example:
        >>> air_floor(np.array([1000.0, 1000.0, 1010.0, 1040.0])), air_floor(np.array([0.0, 5.0])), air_floor(np.arange(1.0, 300.0))
        (1000.0, 0.0, 0.0)
    """
    a = np.asarray(values)
    return 0.0 if a.size == 0 or a.dtype.kind not in "if" else _floor_at(a, float(a.min()))


def _floor_at(a: NDArray, lowest: float) -> float:
    """:func:`air_floor` of ``a`` whose lowest value is ``lowest`` (worked out once by the caller)."""
    if not lowest > 0:
        return 0.0
    sample = a.ravel()[::max(1, a.size // MAX_SAMPLED_VALUES)]
    return lowest if float(np.mean(sample == lowest)) >= FLOOR_SHARE else 0.0


def magnitude(values: NDArray, floor: float | None = None) -> NDArray:
    """An image's values as magnitudes, the background at 0.

    An MR magnitude image holds no value below zero, and the service's steps rely on that: the
    localiser scales a stack by a high percentile, N4 models a multiplicative bias, the image stage
    divides by the brain's median. A file whose values go below zero stores them with an offset (a
    signed export, a z-score, a rescale intercept): its darkest :data:`BACKGROUND_PERCENTILE` % of
    values (of up to :data:`MAX_SAMPLED_VALUES`, the air around the body in a whole field of view) is
    taken as the background and moved to 0, and what lies below is clipped. A fill value
    (:data:`FILL_SHARE`; a tool's padding, far below the image) is no background: it becomes 0, and
    the background level comes from the other values (a fill on 0.5 % of the voxels became the
    background, and at -32768 lifted the whole image so far that no brain was found). An image
    whose lowest value lies above zero is returned as it is, the same array (the stacks of every
    scanner so far, and the training volumes), unless that value is a floor, :data:`FLOOR_SHARE` of
    the values or more (air stored with an offset, :func:`air_floor`): it is moved to 0. A stack's
    localisation, N4 and slices are then the same for the stack stored with any offset or scale.
    ``floor``: the floor to move to 0 where the image has no value below zero, decided elsewhere (a
    streamed stack's, by its first slice, so that its slices keep one offset; values under it clip to 0).

    Example:
        >>> a = np.array([[0.0, 10.0], [20.0, 40.0]], np.float32)
        >>> magnitude(a) is a
        True
        >>> magnitude(a - 1000).tolist(), (magnitude((a - 17.5) / 15.0) * 15).round(4).tolist()   # an offset, a z-score
        ([[0.0, 10.0], [20.0, 40.0]], [[0.0, 10.0], [20.0, 40.0]])
        >>> magnitude(np.array([[-32768.0, 0.0, 10.0], [20.0, 40.0, 5.0]], np.float32)).tolist()   # a fill
        [[0.0, 0.0, 10.0], [20.0, 40.0, 5.0]]
        >>> magnitude(a + 1000).tolist()                                                           # air with an offset
        [[0.0, 10.0], [20.0, 40.0]]
    """
    a = np.asarray(values)
    if a.size == 0 or a.dtype.kind not in "if":
        return values
    if not (lowest := float(a.min())) < 0:
        floor = _floor_at(a, lowest) if floor is None else floor
        return np.maximum(a.astype(np.float32) - np.float32(floor), np.float32(0.0)) if floor > 0 else values
    sample = a.ravel()[::max(1, a.size // MAX_SAMPLED_VALUES)]
    lowest = sample.min()
    rest = sample[sample > lowest]
    fill = (float(np.mean(sample == lowest)) >= FILL_SHARE and rest.size > 0
            and float(rest.min()) - float(lowest) > FILL_GAP * float(rest.max() - rest.min()))
    background = float(np.percentile(rest if fill else sample, BACKGROUND_PERCENTILE, method="lower"))
    out = np.maximum(a.astype(np.float32) - np.float32(min(background, 0.0)), np.float32(0.0))
    if fill:
        out[a == lowest] = 0.0
    return out


def from_sitk(image: sitk.Image) -> Volume:
    """Convert a 3D SimpleITK image (LPS, array ``[k, j, i]``) to a :class:`Volume`."""
    import SimpleITK as sitk
    arr = sitk.GetArrayFromImage(image).transpose(2, 1, 0)
    aff = frames.affine_from_itk(image.GetOrigin(), image.GetSpacing(), image.GetDirection())
    return Volume(arr, aff)


def to_sitk(volume: Volume) -> sitk.Image:
    """Convert a :class:`Volume` to a SimpleITK image (LPS)."""
    import SimpleITK as sitk
    image = sitk.GetImageFromArray(np.ascontiguousarray(np.asarray(volume.array).transpose(2, 1, 0)))
    origin, spacing, direction = frames.itk_from_affine(volume.affine)
    image.SetOrigin(tuple(float(x) for x in origin))
    image.SetSpacing(tuple(float(x) for x in spacing))
    image.SetDirection(tuple(float(x) for x in direction.ravel()))
    return image


def read_volume(path: str | Path) -> Volume:
    """Read a NIfTI/NRRD/MHA file (any format SimpleITK reads) as a :class:`Volume`; a NIfTI file is
    placed by its sform whenever the sform's code is above 0, as the standard says
    (:mod:`service.io.nifti_header`; the service's own files, the atlases)."""
    import SimpleITK as sitk
    nifti = read_transforms(Path(path)) if str(path).endswith((".nii", ".nii.gz")) else None
    with SITK_FILES:
        image = sitk.ReadImage(str(path))
    return placed_by_header(from_sitk(image), nifti)


def placed_by_header(volume: Volume, nifti: NiftiTransforms | None) -> Volume:
    """``volume`` (as SimpleITK read it) placed as its NIfTI header's transforms ``nifti`` say: by the
    sform whenever the sform's code is above 0, with the sform's own voxel sizes, else by the qform
    where its code is above 0, both in millimetres whatever the header's unit, as the standard's
    reference code, nibabel and FSL do (:mod:`service.io.nifti_header`); the transforms kept with
    it. Other files (``nifti`` None), and a header with neither code, as they were read."""
    if nifti is None:
        return volume
    if nifti.sform_code > 0:
        affine = sform_affine(nifti)
    elif nifti.qform_code > 0:
        affine = qform_affine(nifti)
    else:
        affine = volume.affine
    return replace(volume, affine=affine, nifti=nifti)


def write_volume(volume: Volume, path: str | Path) -> None:
    """Write a :class:`Volume`; the format follows the file name (``.nii.gz``, ``.nrrd``, ``.mha``).

    ITK stores axes a hair off right angles (within :data:`~service.geometry.frames.MAX_SHEAR_COS`,
    as a scanner's or converter's rounding leaves them) as the nearest rotation; a NIfTI file then
    gets the volume's own affine as its sform, so that a mask written on an upload's grid lies on
    that grid exactly (the qform keeps the rotation)."""
    import SimpleITK as sitk
    image = to_sitk(volume)
    with SITK_FILES:
        sitk.WriteImage(image, str(path), useCompression=True)
    if str(path).endswith((".nii", ".nii.gz")) and float(frames.axes_cosine(volume.affine[:3, :3])) > EXACT_AXES_COS:
        set_sform(Path(path), volume.affine)


EXACT_AXES_COS = 1e-7
"""Axes closer than this to right angles are stored by ITK as they are (to float32's precision)."""
