"""A reconstruction's atlas frame, re-estimated by the network on slices re-cut from it.

SVR makes a job's slices consistent with each other, but the reconstruction stays in the frame its
starting poses gave it: their common error stays, and after SVR the slices agree with each other
far better than with the truth. The reconstruction, though, is a motion-free brain, and the
network can pose any slice of it:

1. re-cut ``n`` thick slices (3 mm) in random orientations through the central 70 % of its
   brain (where the network errs least), at known poses ``Q_i`` in the reconstruction's frame;
2. preprocess them as the service does (:func:`~service.preprocess.slices.preprocess_slices`) and
   pose them with the network: ``P_i`` in the atlas, each on the branch of the left-right twin
   nearer ``Q_i`` (a single slice cannot tell; the reconstruction's frame can);
3. each slice estimates the frame, ``F_i = P_i Q_i^-1``; a Tukey-weighted Fréchet mean about the
   brain's centre, each weighed by its MC spread, gives ``F``, which moves the volume and every
   refined pose.

Hundreds of clean slices of one brain average the network's per-slice errors down where the
slices of the upload (a few dozen per stack, motion-corrupted) could not. A correction beyond
:data:`MAX_ROTATION_DEG` / :data:`MAX_SHIFT_MM` is reported and not applied (the reconstruction
itself is then unlikely to be a brain the network knows), and none is sought where the job's
stacks do not predict each other well (leave-one-stack-out median NCC under :data:`MIN_FRAME_NCC`):
slices re-cut from a volume that is no coherent brain pose it nowhere in particular.

Example:
    >>> from service.io.volume import Volume
    >>> empty = Volume(np.zeros((8, 8, 8), np.float32), np.eye(4))
    >>> atlas_frame(empty, estimator=None, plane_x_mm=0.0).applied
    False
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from service.geometry import iterators, sampling, se3, twin
from service.geometry.anchors import ed
from service.geometry.pose import about_centre, apply, make_pose, translate
from service.io.volume import Volume
from service.preprocess.slices import preprocess_slices
from service.reconstruction.midline import FrameCorrection
from service.reconstruction.quality import incoherent

if TYPE_CHECKING:                      # the estimator is handed in; nothing of inference runs here
    from service.inference.estimator import PoseEstimator
    from service.reconstruction.pipeline import ReconstructionResult

SLICES = 256
"""Slices re-cut from the reconstruction."""
THICKNESS_MM = 3.0
"""Their thickness (Gaussian PSF FWHM): what the network was validated on."""
CENTRAL_FRACTION = 0.7
"""Planes through this central part of the brain's extent along each normal."""
FOV_MM = 140.0
MIN_MASK_FRACTION = 0.05
MIN_SLICES = 32
MAX_ROTATION_DEG = 20.0
MAX_SHIFT_MM = 20.0
MIN_FRAME_NCC = 0.7
"""The leave-one-stack-out median NCC a job's volume needs for its frame to be re-estimated, above
the coherence floor (:data:`~service.reconstruction.quality.MIN_HELD_OUT_NCC`): re-cut from a
volume that scores below it, the slices pose the frame nowhere in particular and move it the wrong
way, while good volumes score above it (the scores measured: docs/reconstruction.md, "Atlas
frame", and docs/reports/reconstruction-experiments.md)."""


@dataclass
class FrameFit(FrameCorrection):
    """The re-estimated frame (:class:`~service.reconstruction.midline.FrameCorrection`), and

    Attributes:
        slices: slices that voted.
        spread_mm: robust spread of the per-slice estimates (E.D. of the anchor points, MAD-based).
    """

    slices: int = 0
    spread_mm: float = float("nan")

    def report(self) -> dict:
        """The job report's ``atlas_frame`` object."""
        return {**super().report(), "slices": self.slices,
                "spread_mm": round(self.spread_mm, 3) if np.isfinite(self.spread_mm) else None}


def with_frame(result: ReconstructionResult, fit: FrameCorrection) -> ReconstructionResult:
    """``result`` moved by the fit's correction (this module's, or the midline's of
    :mod:`~service.reconstruction.midline`): the volume's affine and every refined pose, so each
    voxel and each slice pixel keep their relation (no resampling)."""
    if not fit.applied:
        return result
    return replace(result, volume=replace(result.volume, affine=fit.correction @ result.volume.affine),
                   atlas_from_voxel_final=fit.correction[None] @ result.atlas_from_voxel_final)


def extent_along(points: NDArray, normals: NDArray, block: int = 16) -> tuple[NDArray, NDArray]:
    """The least and greatest of ``points [P, 3]`` projected on each of ``normals [n, 3]``, ``[n]``
    each, a block of normals at a time (the memory of ``P x block`` projections, not ``P x n``).

    A mask's extremes along any direction lie on its surface (a voxel without a neighbour beyond it
    along the direction), so callers pass those voxels alone.

    Example:
        >>> lo, hi = extent_along(np.array([[0.0, 0, 0], [1, 2, 3]]), np.eye(3))
        >>> lo.tolist(), hi.tolist()
        ([0.0, 0.0, 0.0], [1.0, 2.0, 3.0])
    """
    lo, hi = np.empty(len(normals)), np.empty(len(normals))
    for start in range(0, len(normals), block):
        along = points @ normals[start:start + block].T
        lo[start:start + block], hi[start:start + block] = along.min(axis=0), along.max(axis=0)
    return lo, hi


def recut(volume: Volume, mask: NDArray, n: int, rng: np.random.Generator, size: int,
          pixel_mm: float) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """``n`` thick slices through the central part of ``mask``'s brain: images and masks
    ``[n, size, size]``, their poses ``[n, 4, 4]`` (slice mm -> the volume's world) and the brain's centre."""
    centre = apply(volume.affine, np.argwhere(mask)).mean(axis=0)
    rot = iterators.random_rotations(n, rng, 2 * np.pi)
    surface = apply(volume.affine, np.argwhere(mask & ~ndimage.binary_erosion(mask)))
    lo, hi = extent_along(surface - centre, rot[:, :, 2])
    tz = (lo + hi) / 2 + rng.uniform(-1.0, 1.0, n) * CENTRAL_FRACTION / 2 * (hi - lo)
    poses = make_pose(rot, centre + rot[:, :, 2] * tz[:, None])
    images = sampling.sample_slices(volume.array, volume.affine, poses, size, pixel_mm, thickness_mm=THICKNESS_MM)
    masks = sampling.sample_slices(mask.astype(np.float32), volume.affine, poses, size, pixel_mm) > 0.5
    return images, masks, poses, centre


def atlas_frame(volume: Volume, estimator: PoseEstimator | None, plane_x_mm: float, *, n_slices: int = SLICES,
                mc_samples: int = 100, seed: int = 0, held_out_ncc: float | None = None) -> FrameFit:
    """Re-estimate the atlas frame of a reconstruction (module docstring); ``estimator`` None: not
    applied; ``held_out_ncc``: the job's leave-one-stack-out median NCC (None: not measured)."""
    arr = np.asarray(volume.array, dtype=np.float32)
    positive = arr[arr > 0]
    if estimator is None or positive.size < 1000 or incoherent(held_out_ncc, MIN_FRAME_NCC):
        return FrameFit(np.eye(4), False)
    mask = arr > 0.05 * float(np.percentile(positive, 99))
    info = estimator.info
    pixel_mm = float(info.pixel_spacing_mm)
    size = int(np.ceil(FOV_MM / pixel_mm / 2.0)) * 2
    images, masks, poses, centre = recut(volume, mask, n_slices, np.random.default_rng(seed), size, pixel_mm)
    prep = preprocess_slices(images, masks, (pixel_mm, pixel_mm), int(info.input_size), pixel_mm)
    keep = prep.mask_fraction >= MIN_MASK_FRACTION
    if keep.sum() < MIN_SLICES:
        return FrameFit(np.eye(4), False, slices=int(keep.sum()))
    cut = sampling.recentre(poses, prep.centroid_mm)[keep]
    est = estimator.estimate(prep.inputs[keep], mc_samples)
    net = np.asarray(est.mean, dtype=np.float64)
    mirrored = twin.twin(net, plane_x_mm)
    net = np.where((ed(mirrored, cut) < ed(net, cut))[:, None, None], mirrored, net)
    about = translate(centre)
    each = se3.inverse(about)[None] @ net @ se3.inverse(cut) @ about[None]    # [m, 4, 4] about the centre
    spread = np.maximum(np.nan_to_num(np.asarray(est.spread_mm, dtype=np.float64), nan=1e3), 1.0)
    w = 1.0 / spread ** 2
    frame = se3.frechet_mean(each, w)
    for _ in range(3):
        r = ed(each, frame[None])
        frame = se3.frechet_mean(each, w * se3.tukey_weights(r, max(se3.MAD_SCALE * float(np.median(r)), 1e-6)))
    rotation = float(np.degrees(np.linalg.norm(se3.so3_log(frame[:3, :3]))))
    shift = float(np.linalg.norm(frame[:3, 3]))
    applied = rotation <= MAX_ROTATION_DEG and shift <= MAX_SHIFT_MM
    correction = about_centre(frame, centre) if applied else np.eye(4)
    return FrameFit(correction, applied, rotation, shift, slices=int(keep.sum()),
                    spread_mm=float(1.4826 * np.median(ed(each, frame[None]))))
