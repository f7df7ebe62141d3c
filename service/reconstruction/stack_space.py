"""Where the reconstructed brain sat in each stack's scanner coordinates.

A job's volume lives in atlas space. To overlay it on one of the uploaded stacks in a viewer, or to
compare it with other images of the same session, a user wants it in that stack's scanner (patient)
coordinates. The fetus moves between slices, so there is no one such place: each slice of the stack
has its own map, ``scanner_from_atlas = stack_affine @ inv(atlas_from_voxel)`` (the map the per-slice
``.tfm`` files hold, :mod:`service.reconstruction.export`). A stack's frame is the Fréchet mean of
that map over the stack's slices in the volume, weighed as the volume weighs them: where the brain
was, on average, while that stack was acquired. The rotation is taken about the atlas origin, which
lies in the brain, so the mean is not pulled by the lever of a far scanner origin. ``motion_mm`` says
how far the stack's slices strayed from it (the median over its slices of the mean displacement of
the brain's centre and six points 40 mm from it): the misfit to expect where the overlay meets a
single slice.

Placing the volume there changes only its affine (``scanner_from_atlas @ volume_affine``): the voxels
are the same, so nothing is resampled.

Example (two slices of one stack, 2 mm apart along x about the same frame):
    >>> import numpy as np
    >>> affine = np.diag([1.0, 1.0, 3.0, 1.0])
    >>> atlas_from_voxel = np.stack([np.eye(4), np.eye(4)]); atlas_from_voxel[:, 0, 3] = [-1.0, 1.0]
    >>> atlas_from_voxel = atlas_from_voxel @ affine
    >>> frames = stack_frames(atlas_from_voxel, np.stack([affine, affine]), np.array([0, 0]), np.ones(2))
    >>> np.round(frames[0].scanner_from_atlas[:3, 3], 6).tolist(), round(frames[0].motion_mm, 3)
    ([0.0, 0.0, 0.0], 1.0)
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.geometry import se3
from service.io.nifti_header import NiftiTransforms, qform_from_sform
from service.inference.acceptance import ATLAS_CENTRE_MM

RADIUS_MM = 40.0
"""The points whose displacement ``motion_mm`` averages lie this far from the brain's centre."""


@dataclass(frozen=True)
class StackFrame:
    """One stack's place: ``scanner_from_atlas`` (``4 x 4``, RAS mm, rigid; None where no slice of the
    stack is in the volume), the slices it is the mean of, and ``motion_mm`` (see the module); for a
    stack read from a NIfTI file, its header's ``nifti_codes`` (``qform_code, sform_code``),
    ``qform_from_sform`` (:func:`~service.io.nifti_header.qform_from_sform`: where its qform places
    what its sform, the service's placement, puts at ``p``; None where they agree) and
    ``nifti_spatial_unit`` (``xyzt_units``' distance unit, which ITK scales a qform by), which the
    volume placed in its coordinates takes over, so that every reader places both alike."""

    stack: int
    scanner_from_atlas: NDArray[np.float64] | None
    slices: int
    motion_mm: float | None
    nifti_codes: tuple[int, int] | None = None
    qform_from_sform: NDArray[np.float64] | None = None
    nifti_spatial_unit: int | None = None

    def as_json(self) -> dict:
        """The report's entry (``stack_frames[]``)."""
        return {"stack": self.stack, "slices": self.slices,
                "scanner_from_atlas": None if self.scanner_from_atlas is None else self.scanner_from_atlas.tolist(),
                "motion_mm": None if self.motion_mm is None else round(float(self.motion_mm), 3),
                "nifti_codes": None if self.nifti_codes is None else list(self.nifti_codes),
                "qform_from_sform": None if self.qform_from_sform is None else self.qform_from_sform.tolist(),
                "nifti_spatial_unit": self.nifti_spatial_unit}


class NoStackFrame(LookupError):
    """A job has no such stack, or no place for it (no slice of it in the volume, or a report of a job
    made before stack frames existed); the message says which."""


def scanner_from_atlas(atlas_from_voxel: ArrayLike, stack_affine: ArrayLike) -> NDArray[np.float64]:
    """``[n, 4, 4]`` RAS transforms atlas mm -> the stack's scanner mm (``stack_affine @ inv(atlas_from_voxel)``)."""
    return np.asarray(stack_affine, np.float64) @ np.linalg.inv(np.asarray(atlas_from_voxel, np.float64))


def _points() -> NDArray[np.float64]:
    """``[4, 7]`` homogeneous points: the brain's centre and six points ``RADIUS_MM`` about it."""
    offsets = np.concatenate([np.zeros((1, 3)), RADIUS_MM * np.eye(3), -RADIUS_MM * np.eye(3)])
    return np.vstack([(ATLAS_CENTRE_MM + offsets).T, np.ones(len(offsets))])


def stack_frames(atlas_from_voxel: ArrayLike, stack_affine: ArrayLike, stack_index: ArrayLike,
                 weights: ArrayLike) -> list[StackFrame]:
    """Each stack's frame (see the module) from its slices' final ``atlas_from_voxel [n, 4, 4]``, their
    stacks' ``stack_affine [n, 4, 4]`` (voxel -> scanner RAS) and ``stack_index [n]``; a slice with
    weight 0 (not in the volume) takes no part, nor one whose map mirrors (a pose of the other
    handedness than its stack's file: no rotation is near it). Stacks ``0 .. max(stack_index)``, in order."""
    pose = scanner_from_atlas(atlas_from_voxel, stack_affine)
    stack, w = np.asarray(stack_index, np.int64), np.nan_to_num(np.asarray(weights, np.float64))
    w = np.where(np.linalg.det(pose[:, :3, :3]) > 0, w, 0.0) if len(pose) else w
    points = _points()
    out = []
    for s in range(int(stack.max()) + 1 if len(stack) else 0):
        take = (stack == s) & (w > 0)
        if not take.any():
            out.append(StackFrame(s, None, 0, None))
            continue
        rigid = _nearest_rigid(pose[take])
        mean = se3.frechet_mean(rigid, w[take])
        moved = np.linalg.norm((rigid @ points)[:, :3] - (mean @ points)[None, :3], axis=1).mean(axis=1)
        out.append(StackFrame(s, mean, int(take.sum()), float(np.median(moved))))
    return out


def with_header(frame: StackFrame, header: NiftiTransforms | None) -> StackFrame:
    """``frame`` with its stack's NIfTI header's transforms (None: the stack was not read from NIfTI):
    the codes, the qform's move and the distance unit that a volume placed in the stack's coordinates
    takes over."""
    if header is None:
        return frame
    return replace(frame, nifti_codes=(int(header.qform_code), int(header.sform_code)),
                   qform_from_sform=qform_from_sform(header), nifti_spatial_unit=int(header.spatial_unit))


def _nearest_rigid(transforms: NDArray) -> NDArray[np.float64]:
    """``[n, 4, 4]`` the rigid transforms nearest to ``transforms`` of positive determinant (their
    rotation parts projected onto SO(3)); the per-slice maps are rigid up to the rounding of the
    files' affines."""
    u, _, vt = np.linalg.svd(transforms[:, :3, :3])
    out = np.array(transforms, np.float64, copy=True)
    out[:, :3, :3] = u @ vt
    out[:, 3] = [0.0, 0.0, 0.0, 1.0]
    return out


def stack_frame(report: dict, stack: int) -> StackFrame:
    """Stack ``stack``'s frame as a job's report holds it (``stack_frames``); raises
    :class:`NoStackFrame` where there is none."""
    entries = report.get("stack_frames")
    if entries is None:
        raise NoStackFrame("the job's report has no stack frames (a job of an earlier version)")
    if not 0 <= stack < len(entries):
        raise NoStackFrame(f"stack {stack}: the job's stacks are 0-{len(entries) - 1}")
    entry = entries[stack]
    if entry.get("scanner_from_atlas") is None:
        raise NoStackFrame(f"stack {stack} has no slice in the volume: no place to put the volume by")
    codes, move = entry.get("nifti_codes"), entry.get("qform_from_sform")        # absent: a job of an earlier version
    unit = entry.get("nifti_spatial_unit")
    return StackFrame(stack, np.asarray(entry["scanner_from_atlas"], np.float64), int(entry.get("slices") or 0),
                      entry.get("motion_mm"), None if codes is None else (int(codes[0]), int(codes[1])),
                      None if move is None else np.asarray(move, np.float64), None if unit is None else int(unit))


def in_stack_space(volume_affine: ArrayLike, frame: StackFrame) -> NDArray[np.float64]:
    """The affine that places a volume of atlas space (``volume_affine``: voxel -> atlas RAS) in the
    stack's scanner coordinates (voxel -> scanner RAS)."""
    if frame.scanner_from_atlas is None:
        raise NoStackFrame(f"stack {frame.stack} has no slice in the volume: no place to put the volume by")
    return frame.scanner_from_atlas @ np.asarray(volume_affine, np.float64)
