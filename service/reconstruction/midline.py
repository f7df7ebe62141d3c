"""A reconstruction's own mid-sagittal plane, put on the atlas plane.

The atlas space is left-right symmetric about ``x = x0``. A brain is nearly symmetric about its
own mid-sagittal plane, so the plane can be read off the volume itself, without an atlas: a brain
moved ``G`` away from the symmetric position is its own mirror image (across ``x = x0``) moved
``G^-2`` away, because the mirror reverses a shift along x and turns about y and z. Rigidly
registering the volume onto its mirror image gives ``G^-2``; half of it, ``G^-1`` (exactly for a
shift or a turn alone; combined, to within their product: 0.1 mm for 3 deg and 2 mm), moves the
midline onto the plane. A mirror cannot see a turn about x or shifts in y and z: those stay as the
network's atlas frame put them (:mod:`~service.reconstruction.atlas_frame`).

A correction beyond :data:`MAX_ROTATION_DEG` / :data:`MAX_SHIFT_MM` is reported and not applied
(the volume is then unlikely to be a whole, symmetric-looking brain), and none is sought where the
job's stacks do not predict each other (leave-one-stack-out median NCC under
:data:`~service.reconstruction.quality.MIN_HELD_OUT_NCC`): a volume that is no coherent brain has no midline to trust.

Example (a volume symmetric about the plane needs no correction):
    >>> import numpy as np
    >>> from service.io.volume import Volume
    >>> x = np.linspace(-1.0, 1.0, 24)
    >>> ball = np.exp(-4.0 * (x[:, None, None] ** 2 + x[None, :, None] ** 2 + (x[None, None, :] - 0.3) ** 2))
    >>> affine = np.diag([2.0, 2.0, 2.0, 1.0]); affine[:3, 3] = -23.0
    >>> fit = midline_fit(Volume(ball.astype(np.float32), affine), plane_x_mm=0.0)
    >>> fit.applied, fit.rotation_deg < 0.3, fit.shift_mm < 0.3
    (True, True, True)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
from numpy.typing import NDArray
from scipy import ndimage

from service.geometry import se3, twin
from service.geometry.frames import ras_transform_from_lps
from service.geometry.pose import about_centre, translate
from service.io.volume import Volume, to_sitk
from service.reconstruction.quality import incoherent

MAX_ROTATION_DEG = 10.0
MAX_SHIFT_MM = 5.0
BRAIN_FRACTION = 0.05
"""Voxels above this fraction of the 99th intensity percentile are the brain (as the atlas frame's)."""


@dataclass
class FrameCorrection:
    """A rigid move of a reconstruction and of every refined pose with it.

    Attributes:
        correction: ``4 x 4`` atlas <- the volume's frame (identity when not applied).
        applied: whether ``correction`` is to be applied.
        rotation_deg, shift_mm: the correction's rotation and its shift of the brain's centre.
    """

    correction: NDArray[np.float64]
    applied: bool
    rotation_deg: float = 0.0
    shift_mm: float = 0.0

    def report(self) -> dict:
        """The job report's object for this step (``midline``)."""
        return {"applied": self.applied, "rotation_deg": round(self.rotation_deg, 3),
                "shift_mm": round(self.shift_mm, 3)}


def registration_method(sampling: float = 0.1, iterations: int = 200, relaxation: float = 0.5,
                        finest_sigma_mm: float = 0.5) -> sitk.ImageRegistrationMethod:
    """SimpleITK's registration as this project uses it: correlation on a random ``sampling`` of the
    voxels, linear interpolation, a 4-2-1 pyramid (smoothing 2, 1 and ``finest_sigma_mm`` mm), and
    regular-step gradient descent that stops on its step (1e-4), not on ITK's default gradient
    tolerance, which stops turns short (a 3 deg turn found as 1.7). The caller sets the transform."""
    reg = sitk.ImageRegistrationMethod()
    reg.SetMetricAsCorrelation()
    reg.SetMetricSamplingStrategy(reg.RANDOM)
    reg.SetMetricSamplingPercentage(sampling, 1)
    reg.SetInterpolator(sitk.sitkLinear)
    reg.SetOptimizerAsRegularStepGradientDescent(1.0, 1e-4, iterations, relaxationFactor=relaxation,
                                                 gradientMagnitudeTolerance=1e-8)
    reg.SetOptimizerScalesFromPhysicalShift()
    reg.SetShrinkFactorsPerLevel([4, 2, 1])
    reg.SetSmoothingSigmasPerLevel([2.0, 1.0, finest_sigma_mm])
    reg.SmoothingSigmasAreSpecifiedInPhysicalUnitsOn()
    return reg


def register_rigid(fixed: Volume, moving: Volume, fixed_mask: NDArray, moving_mask: NDArray,
                   centre_mm: NDArray) -> NDArray[np.float64]:
    """``4 x 4`` atlas RAS: the rigid map from a point of ``fixed`` to the same anatomy in ``moving``
    (correlation of the masked images, :func:`registration_method`, from the identity about
    ``centre_mm``)."""
    f, m = (sitk.Cast(to_sitk(Volume(v.array * (k > 0.5), v.affine)), sitk.sitkFloat32)
            for v, k in ((fixed, fixed_mask), (moving, moving_mask)))
    start = sitk.Euler3DTransform()
    start.SetCenter([-float(centre_mm[0]), -float(centre_mm[1]), float(centre_mm[2])])     # RAS -> LPS
    reg = registration_method()
    reg.SetInitialTransform(start, inPlace=False)
    tx = reg.Execute(f, m)
    tx = sitk.Euler3DTransform(tx.GetNthTransform(0) if isinstance(tx, sitk.CompositeTransform) else tx)
    lps = np.eye(4)
    lps[:3, :3] = np.reshape(tx.GetMatrix(), (3, 3))
    c, t = np.array(tx.GetCenter()), np.array(tx.GetTranslation())
    lps[:3, 3] = t + c - lps[:3, :3] @ c
    return ras_transform_from_lps(lps)


def mirror_image(array: NDArray, affine: NDArray, plane_x_mm: float) -> NDArray[np.float32]:
    """``array`` (voxel -> atlas ``affine``) mirrored across ``x = plane_x_mm``, on its own grid."""
    to_voxel = np.linalg.inv(affine) @ twin.mirror(plane_x_mm) @ affine
    return ndimage.affine_transform(np.asarray(array, np.float32), to_voxel[:3, :3], to_voxel[:3, 3], order=1)


def midline_offset(volume: Volume, mask: NDArray, plane_x_mm: float) -> tuple[NDArray[np.float64], NDArray]:
    """``(H, centre)``: ``H`` (``4 x 4`` about the brain's ``centre``, atlas mm) puts the midline of the
    brain in ``mask`` on the plane: half its registration onto its mirror image (the module)."""
    centre = np.argwhere(mask > 0.5).mean(axis=0) @ volume.affine[:3, :3].T + volume.affine[:3, 3]
    mirrored = Volume(mirror_image(volume.array, volume.affine, plane_x_mm), volume.affine)
    onto = register_rigid(volume, mirrored, mask, mirror_image(mask, volume.affine, plane_x_mm), centre)
    about = translate(centre)
    return se3.exp(0.5 * se3.log(se3.inverse(about) @ onto @ about)), centre


def midline_fit(volume: Volume, plane_x_mm: float, held_out_ncc: float | None = None) -> FrameCorrection:
    """The correction that puts a reconstruction's midline on the atlas plane (see the module);
    ``held_out_ncc``: the job's leave-one-stack-out median NCC (None: not measured, e.g. one stack)."""
    arr = np.asarray(volume.array, dtype=np.float32)
    positive = arr[arr > 0]
    if positive.size < 1000 or incoherent(held_out_ncc):
        return FrameCorrection(np.eye(4), False)
    mask = (arr > BRAIN_FRACTION * float(np.percentile(positive, 99))).astype(np.float32)
    try:
        half, centre = midline_offset(volume, mask, plane_x_mm)
    except RuntimeError:                # ITK gives up (e.g. too few voxels overlap): nothing to apply
        return FrameCorrection(np.eye(4), False)
    rotation = float(np.degrees(np.linalg.norm(se3.so3_log(half[:3, :3]))))
    shift = float(np.linalg.norm(half[:3, 3]))
    applied = rotation <= MAX_ROTATION_DEG and shift <= MAX_SHIFT_MM
    correction = about_centre(half, centre) if applied else np.eye(4)
    return FrameCorrection(correction, applied, rotation, shift)
