"""What a reconstruction job makes of its slices, from the starting poses to the poses it returns.

One sequence, run by the job worker (:mod:`service.jobs.worker`) and by the experiments that measure
it: the never-worse paths (:mod:`~service.reconstruction.never_worse`), the slices left out of the
volume placed (:mod:`~service.reconstruction.left_out`), the atlas frame re-estimated by the network
and the midline put on the atlas plane (:mod:`~service.reconstruction.atlas_frame`,
:mod:`~service.reconstruction.midline`; ``atlas_frame=False`` skips both), and each returned pose's
expected error (:mod:`~service.reconstruction.pose_errors`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from service.io.volume import Volume
from service.preprocess.bias import n4_correct
from service.reconstruction.atlas_frame import FrameFit, atlas_frame, with_frame
from service.reconstruction.left_out import LeftOutPlacement, VolumeReference, place_left_out
from service.reconstruction.midline import FrameCorrection, midline_fit
from service.reconstruction.held_out import coherence_score, held_out_score, stack_held_out, without_stacks_apart
from service.reconstruction.never_worse import reconstruct_never_worse
from service.reconstruction.config import ReconstructionConfig
from service.reconstruction.grid import bounds_of, check_volume_size, make_grid
from service.reconstruction.pipeline import ReconstructionResult
from service.reconstruction.pose_errors import refined_expected_errors, refined_summary, roles
from service.reconstruction.slices import SliceSet, StackInput

if TYPE_CHECKING:                      # the estimator is handed in; nothing of inference runs here
    from service.consistency.slice_order import SliceOrder
    from service.inference.estimator import PoseEstimator


@dataclass
class RefinedJob:
    """Output of :func:`refine_job`.

    Attributes:
        result: the reconstruction, its volume and every slice's pose in the atlas frame the job settles.
        left_out: where the slices left out of the volume went (its poses before the frame steps).
        frame: the atlas-frame fit (None: not sought).
        midline: the midline fit (None: not sought).
        role: ``[n]`` each slice's role (:func:`~service.reconstruction.pose_errors.roles`).
        areas_mm2: ``[n]`` each slice's brain section.
        expected_error_mm: ``[n]`` each returned pose's expected E.D. (NaN: none).
        starting_error_mm: ``[n]`` the starting poses' expected E.D. (NaN: none known).
    """

    result: ReconstructionResult
    left_out: LeftOutPlacement
    frame: FrameFit | None
    midline: FrameCorrection | None
    role: NDArray[np.int64]
    areas_mm2: NDArray[np.float64]
    expected_error_mm: NDArray[np.float64]
    starting_error_mm: NDArray[np.float64]

    def report(self) -> dict:
        """The job report's fields for these steps."""
        out = {"left_out_placed_by_stack_motion": int(self.left_out.moved.sum()),
               "left_out_placed_by_volume": int(self.left_out.registered.sum()),
               "refined_poses": refined_summary(self.role, self.expected_error_mm, self.starting_error_mm)}
        if self.frame is not None and self.midline is not None:
            out.update(atlas_frame=self.frame.report(), midline=self.midline.report())
        return out


def bias_corrected_stacks(volumes: Sequence[Volume], masks: Sequence[NDArray]) -> list[Volume]:
    """Each stack as a job reconstructs it: its coil's bias field taken out by N4
    (:func:`~service.preprocess.bias.n4_correct`, fitted over the box around ``masks``, the brain
    the job reconstructs, and a margin; outside the box the stack stays as uploaded); a stack
    without brain pixels as it is.

    A field fixed in the scanner is smooth in the stack's voxel grid however the fetus moves, and
    changes each stack's brightness across the brain along another direction: the stacks then
    disagree with each other by more than their anatomy, and the stack-to-stack registration,
    which compares whole stacks, follows the fields (docs/reconstruction.md, "What a job does").
    What N4 leaves, a gain per slice and the shading the motion adds, is the per-slice intensity
    matching's (:mod:`~service.reconstruction.intensity`).

    Args:
        volumes: the stacks as uploaded.
        masks: each stack's brain on its grid (nonzero: brain).

    Returns:
        The corrected stacks, on the same grids with the same headers.

    Example (a stack shaded from one side to the other comes back nearly flat):
        >>> import numpy as np
        >>> ramp = np.linspace(0.7, 1.3, 32, dtype=np.float32)[:, None, None] * np.ones((32, 32, 8), np.float32)
        >>> stack = Volume(100 * ramp, np.diag([2.0, 2.0, 4.0, 1.0]))
        >>> [flat] = bias_corrected_stacks([stack], [np.ones(ramp.shape, bool)])
        >>> a = flat.array[4:-4, 4:-4]
        >>> bool(a.max() / a.min() < 1.2)
        True
    """
    return [replace(v, array=n4_correct(v, m)) if np.any(m) else v for v, m in zip(volumes, masks)]


def refine_job(slice_set: SliceSet, stacks: Sequence[StackInput], starting_error_mm: NDArray, *,
               estimator: PoseEstimator | None, plane_x_mm: float, resolution_mm: float, svr_iterations: int,
               orders: Sequence[SliceOrder | None] = (), frame_steps: bool = True, mc_samples: int = 100,
               progress: Callable[[str, float], None] | None = None,
               frame_error_mm: NDArray | None = None) -> RefinedJob:
    """The job's steps on ``slice_set`` (made from ``stacks``, as
    :meth:`~service.reconstruction.slices.SliceSet.from_stacks` takes them) from its starting poses,
    whose expected errors are ``starting_error_mm`` (``[n]``, NaN: none known).

    Args:
        estimator: the pose model the atlas frame re-poses slices with (None: the frame stays, reported
            not applied).
        plane_x_mm: its atlas mid-sagittal plane.
        resolution_mm, svr_iterations: the volume's spacing and the slice-to-volume rounds.
        orders: per stack, what is known of its acquisition order (empty: nothing).
        frame_steps: run the atlas-frame and midline steps.
        progress: ``(stage, fraction of the steps done)`` as each stage begins.
        frame_error_mm: ``[n]`` the request's frame error the starting prediction added to each
            slice's expected error and ``starting_error_mm`` leaves out
            (:mod:`service.consistency.frame_error`): the slices are weighed without it, and a
            refined pose keeps it where no frame step placed the volume again.
    """
    report = progress or (lambda stage, fraction: None)
    if slice_set.n_pixels:                             # the volume where the slices start: refused now, not later
        check_volume_size(make_grid(resolution_mm, bounds_of(slice_set.positions(), ReconstructionConfig().margin_mm)))
    config = ReconstructionConfig(symmetry_plane_x_mm=plane_x_mm, slice_orders=tuple(orders) or None)
    result = reconstruct_never_worse(slice_set, resolution_mm=resolution_mm, svr_iterations=svr_iterations,
                                     progress=report, config=config)
    result = without_stacks_apart(slice_set, result, lambda kept, named: reconstruct_never_worse(
        kept, resolution_mm=resolution_mm, svr_iterations=svr_iterations, config=config,
        progress=lambda stage, fraction: report(f"without stack {named}: {stage}", 1.0)))
    reference = VolumeReference.of(result, stacks)
    left_out = place_left_out(slice_set, result.atlas_from_voxel_final, result.included, starting_error_mm,
                              plane_x_mm=plane_x_mm, orders=list(orders) or None, volume=reference,
                              starting=slice_set.atlas_from_voxel)
    areas = reference.areas_mm2
    del reference                                   # every slice's pixels and the blurred volume: done with
    result = replace(result, atlas_from_voxel_final=left_out.poses)
    frame, midline = None, None
    if frame_steps:
        report("atlas frame", 1.0)
        frame = atlas_frame(result.volume, estimator, plane_x_mm, mc_samples=mc_samples,
                            held_out_ncc=coherence_score(result))
        result = with_frame(result, frame)
        report("midline", 1.0)
        midline = midline_fit(result.volume, plane_x_mm, coherence_score(result))
        result = with_frame(result, midline)
    role = roles(result.included, left_out.moved, left_out.registered)
    framed = frame is not None and frame.applied
    unplaced = starting_error_mm if framed or frame_error_mm is None else np.hypot(starting_error_mm, frame_error_mm)
    expected = refined_expected_errors(role, left_out.ncc, areas, unplaced,
                                       held_out_ncc=held_out_score(result), framed=framed,
                                       stack_held_out_ncc=stack_held_out(result, slice_set.stack_index))
    return RefinedJob(result, left_out, frame, midline, role, areas, expected,
                      np.asarray(starting_error_mm, np.float64))
