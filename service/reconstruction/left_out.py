"""The slices a job leaves out of its volume, placed by their stack's motion through the slices in it
or registered to the volume.

A job reconstructs from the slices ``/v1/predict`` accepted; the others (and those the job itself
excludes) are not in the volume, and keep the pose the prediction gave them: the network's, fused
with their stack-mates' by the stack stage, some millimetres off. The slices in the volume come out
within about a millimetre of each other. The stack's motion model
(:func:`~service.consistency.stack_fit.fit_stack`, a Gaussian process over acquisition time) is fitted
again with those refined slices as nearly exact observations and the left-out ones at their
predicted expected errors, all independent (the network's errors are alike on neighbouring slices,
the volume's placements are not), and a left-out slice takes the model's posterior pose where the motion
around it is smooth: where the model predicts each slice of the volume within
:data:`SMOOTH_MM` of where the volume put it, over :data:`REACH` acquisitions on either side of the
left-out slice's time. Across a sudden move of the fetus the model bends between the two sides;
there a left-out slice takes the pose of the placed slice acquired next to it on one side where its
own prediction clearly lies on that side (:func:`beside_a_jump`), and otherwise keeps its predicted
pose, as it does in a stack whose motion is independent from slice to slice (where no neighbour
predicts another).

Given the job's volume (:class:`VolumeReference`), every left-out slice whose brain section is large
enough (:data:`MIN_AREA_MM2`) is then registered to it from a few starts: its pose so far, the
motion model's, and the placed slices acquired next to it on either side. The registered pose with
the highest NCC is taken where that NCC comes near the placed slices' (:data:`NCC_RATIO`), clearly
above the slice's own so far (:data:`NCC_GAIN`), over a move beyond the registration's scatter
(:data:`MIN_MOVE_MM`) (:func:`register_left_out`). Several starts, because from a start beyond the
registration's reach a slice settles in a poorer optimum (lower NCC) than from the right side of a
jump; large sections only, because a cap of the brain fits the volume about as well at poses
centimetres apart. A volume that is no coherent brain (its stacks do not predict each other,
:func:`~service.reconstruction.quality.incoherent`) places no slice: a slice's best fit to it says
nothing of where the slice belongs, and takes it further off.

Example (a rigid stack of 12 slices, the volume placed 10 of them; the two others start 6 mm off
and take the stack's pose):
    >>> import numpy as np
    >>> from service.io.volume import Volume
    >>> from service.reconstruction.slices import SliceSet
    >>> vol = Volume(np.ones((16, 16, 12), np.float32), np.diag([2.0, 2.0, 3.0, 1.0]))
    >>> poses = np.repeat(vol.affine[None], 12, 0)
    >>> off = poses.copy(); off[[3, 8], 0, 3] += 6.0
    >>> ss = SliceSet.from_stacks([(vol, None, off, np.ones(12, bool))])
    >>> inside = np.ones(12, bool); inside[[3, 8]] = False
    >>> out = place_left_out(ss, off, inside, np.full(12, 8.0), plane_x_mm=None)
    >>> out.moved.nonzero()[0].tolist(), bool(np.abs(out.poses[[3, 8], 0, 3]).max() < 0.5)
    ([3, 8], True)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.consistency.slice_order import SliceOrder
from service.geometry.anchors import ed
from service.reconstruction.forward import inplane_sigma_mm
from service.reconstruction.grid import Grid
from service.reconstruction.held_out import coherence_score
from service.reconstruction.pipeline import ReconstructionResult
from service.reconstruction.quality import incoherent
from service.reconstruction.registration import RegistrationResult, blurred_volume, register_slices
from service.reconstruction.slices import SliceSet, StackInput
from service.reconstruction.stack_rigid import fit_stack_rigid, frame_from_scanner

PLACED_MM = 1.0
"""The expected E.D. the motion model gives a slice the volume placed: about how far the slices in a
job's volume lie from the truth in the acquisition's own frame (docs/reports/reconstruction-experiments.md,
"Limits, measured")."""
SMOOTH_MM = 2.0
"""A left-out slice follows the model where it predicts every slice of the volume within this many
mm of its refined pose over :data:`REACH` acquisitions on either side."""
REACH = 2
"""Acquisitions on either side of a left-out slice whose slices in the volume must agree with the model."""
SMOOTH_SHARE = 0.5
"""A stack whose model predicts at least this share of its placed slices within :data:`SMOOTH_MM`
moves smoothly but for its jumps (:func:`beside_a_jump`); under independent motion none are."""
SIDE_RATIO = 0.5
"""A left-out slice beside a jump takes the side whose neighbour lies under this times as far from
its predicted pose as the other side's (:func:`beside_a_jump`)."""
MIN_AREA_MM2 = 600.0
"""A left-out slice is registered to the volume when its brain section covers at least this area
(about a 28 mm disc): smaller sections (the brain's caps) fit the volume as well at poses
centimetres from the truth."""
START_REACH = 3
"""The placed slices acquired within this many acquisitions of a left-out one give it a start."""
NCC_RATIO = 0.9
"""A left-out slice takes its registered pose where its NCC with the volume reaches this fraction of
the placed slices' median NCC (by the same measure): a slice that fits the volume nearly as well as
the slices that made it (docs/reports/reconstruction-experiments.md)."""
NCC_GAIN = 0.03
"""...and where it fits the volume by at least this much better than the slice's pose so far: a slice
the earlier rules placed well gains a few thousandths, within the registration's own scatter."""
MIN_MOVE_MM = 2.0
"""...and where it moves the slice's pixels this far on average: nearer, the registration's own
scatter about the volume's optimum is as large as the move."""
REGISTRATION_STEP_MM = 2.0
"""The registration's first trust radius (mm == degrees)."""
REGISTRATION_ITERATIONS = 30
"""The registration's iterations from each start at most."""


@dataclass
class LeftOutPlacement:
    """Output of :func:`place_left_out`.

    Attributes:
        poses: ``[n, 4, 4]`` every slice's ``atlas_from_voxel``: the given ones, the moved slices' replaced.
        moved: ``[n]`` the left-out slices placed by their stack's motion.
        beside_jump: ``[n]`` those of them that took a neighbour's pose beside a jump (:func:`beside_a_jump`).
    """

    poses: NDArray[np.float64]
    moved: NDArray[np.bool_]
    beside_jump: NDArray[np.bool_]
    registered: NDArray[np.bool_]
    """``[n]`` the left-out slices that took their pose from the volume (:class:`VolumeReference`);
    ``moved`` does not count them."""
    ncc: NDArray[np.float64]
    """``[n]`` every slice's NCC with the volume simulated at its pose in ``poses``, all by one measure
    (:meth:`VolumeReference.ncc`; NaN without a volume, or for a slice with too few brain pixels)."""


@dataclass
class VolumeReference:
    """The job's volume, and every slice's pixels: what the left-out slices are registered to.

    Attributes:
        array: ``[I, J, K]`` the volume on ``grid``.
        grid: its grid.
        slices: the slice set of every slice with its pixels (``include`` where it has brain pixels),
            in the order of the job's.
        coherent: the volume is a coherent brain (its stacks predict each other,
            :func:`~service.reconstruction.quality.incoherent`); an incoherent one places no slice:
            a slice's best fit to it says nothing of where the slice belongs.
    """

    array: NDArray
    grid: Grid
    slices: SliceSet
    coherent: bool = True

    @classmethod
    def of(cls, result: ReconstructionResult, stacks: Sequence[StackInput]) -> VolumeReference:
        """The volume of a job's ``result``, and every slice of the job's ``stacks`` (as
        :meth:`~service.reconstruction.slices.SliceSet.from_stacks` takes them; every slice included)."""
        return cls(result.volume.array, result.grid,
                   SliceSet.from_stacks([(v, m, mats, np.ones(len(mats), bool)) for v, m, mats, _ in stacks]),
                   not incoherent(coherence_score(result)))

    @cached_property
    def areas_mm2(self) -> NDArray[np.float64]:
        """``[n]`` each slice's brain section (mm²)."""
        return self.slices.pixel_counts() * self.slices.pixel_mm ** 2

    @cached_property
    def blur_sigma_mm(self) -> float:
        """The slices' in-plane PSF, as the registration blurs the volume for them."""
        return inplane_sigma_mm(self.slices)

    @cached_property
    def blurred(self) -> NDArray[np.float32]:
        """The volume blurred in-plane once, for every registration and measure against it."""
        return blurred_volume(self.array, self.grid, self.blur_sigma_mm)

    def register(self, start: NDArray, active: NDArray, iterations: int) -> RegistrationResult:
        """Register the ``active`` slices from ``start`` (``[n, 4, 4]``) to the volume (0 iterations:
        their NCC there)."""
        return register_slices(self.blurred, self.grid, self.slices, start, active=active,
                               max_iterations=iterations, step_mm=REGISTRATION_STEP_MM,
                               blur_sigma_mm=self.blur_sigma_mm, blurred=True)

    def ncc(self, poses: NDArray) -> NDArray[np.float64]:
        """``[n]`` every slice's NCC with the volume simulated at ``poses`` (NaN: too few brain pixels)."""
        return self.register(poses, self.slices.include, 0).ncc


def place_left_out(slices: SliceSet, refined: ArrayLike, placed: ArrayLike, expected_error_mm: ArrayLike, *,
                   plane_x_mm: float | None, orders: Sequence[SliceOrder] | None = None,
                   volume: VolumeReference | None = None, starting: ArrayLike | None = None) -> LeftOutPlacement:
    """Move the left-out slices that their stack's motion places (module docstring).

    Args:
        slices: the job's slice set (stack geometry; a left-out slice needs no pixels).
        refined: ``[n, 4, 4]`` the job's ``atlas_from_voxel`` of every slice.
        placed: ``[n]`` bool, the slices in the volume (placed by it).
        expected_error_mm: ``[n]`` the predicted poses' expected E.D. (NaN: not posed, e.g. an empty
            slice; such a slice stays where it is).
        plane_x_mm: the atlas mid-sagittal plane of the poses (None: no twins).
        orders: per stack, what is known of its acquisition order (default: the stage chooses).
        volume: the job's volume to register the left-out slices to (None, or one that is not
            ``coherent``: motion only; the NCC is measured against any volume given).
        starting: ``[n, 4, 4]`` the poses the job started from: the left-out slices start from these,
            the poses ``expected_error_mm`` is of (None: from ``refined``). A path that registered a
            slice and then left it out of its volume leaves it where nothing vouches for it (far
            from where it started, on a whole-uterus scene).
    """
    poses = np.array(refined, dtype=np.float64)
    inside = np.asarray(placed, bool)
    expected = np.asarray(expected_error_mm, dtype=np.float64)
    left_out = ~inside & np.isfinite(expected)
    if starting is not None:
        poses[left_out] = np.asarray(starting, dtype=np.float64)[left_out]
    moved = np.zeros(len(poses), bool)
    if not left_out.any() or not inside.any():
        return LeftOutPlacement(poses, moved, moved.copy(), moved.copy(), final_ncc(volume, poses))
    frames = frame_from_scanner(slices)
    fit = fit_stack_rigid(replace(slices, include=inside | left_out), poses, plane_x_mm=plane_x_mm,
                          use=inside | left_out, orders=orders, frames=frames,
                          expected_error_mm=np.where(inside, PLACED_MM, expected), error_correlations=(0.0,))
    for k in np.flatnonzero(left_out & np.isfinite(fit.times)):
        near = inside & (slices.stack_index == slices.stack_index[k]) & (np.abs(fit.times - fit.times[k]) <= REACH)
        moved[k] = bool(near.any()) and float(np.nanmax(fit.distance_mm[near])) <= SMOOTH_MM
    poses[moved] = fit.motion_poses[moved]
    beside = beside_a_jump(slices, frames, poses, inside, left_out & ~moved & np.isfinite(fit.times), fit.times,
                           fit.distance_mm, expected)
    jumped = np.zeros(len(poses), bool)
    for k, j in beside.items():
        poses[k] = poses[j]
        jumped[k] = True
    registered = np.zeros(len(poses), bool)
    if volume is not None and volume.coherent:
        registered = register_left_out(volume, poses, fit.motion_poses, inside, left_out, slices.stack_index,
                                       fit.times)
    return LeftOutPlacement(poses, (moved | jumped) & ~registered, jumped & ~registered, registered,
                            final_ncc(volume, poses))


def final_ncc(volume: VolumeReference | None, poses: NDArray) -> NDArray[np.float64]:
    """``[n]`` :meth:`VolumeReference.ncc` at ``poses`` (NaN without a volume)."""
    return np.full(len(poses), np.nan) if volume is None else volume.ncc(poses)


def register_left_out(volume: VolumeReference, poses: NDArray, motion_poses: NDArray, inside: NDArray,
                      left_out: NDArray, stack_index: NDArray, times: NDArray) -> NDArray[np.bool_]:
    """Register the left-out slices with a large enough brain section to ``volume`` from each start
    (module docstring) and move those whose best NCC reaches :data:`NCC_RATIO` of the placed slices'
    median and exceeds their NCC so far by :data:`NCC_GAIN`, over a move of :data:`MIN_MOVE_MM` at
    least; ``poses`` is updated in place. Returns the slices moved."""
    ref = volume.slices
    candidates = left_out & ref.include & (volume.areas_mm2 >= MIN_AREA_MM2)
    moved = np.zeros(len(poses), bool)
    if not candidates.any():
        return moved
    register = volume.register
    now = register(poses, inside | candidates, 0).ncc
    placed_ncc = now[inside & np.isfinite(now)]
    if not len(placed_ncc):
        return moved
    best_pose, best = poses.copy(), np.full(len(poses), -np.inf)
    for start in [poses, motion_poses, *neighbour_starts(poses, inside, candidates, stack_index, times)]:
        ok = candidates & np.isfinite(start[:, 0, 0])
        if not ok.any():
            continue
        reg = register(np.where(ok[:, None, None], start, poses), ok, REGISTRATION_ITERATIONS)
        better = ok & reg.registered & (np.nan_to_num(reg.ncc, nan=-np.inf) > best)
        best_pose[better], best[better] = reg.atlas_from_voxel[better], reg.ncc[better]
    moved = (candidates & (best >= NCC_RATIO * np.median(placed_ncc))
             & (best >= np.nan_to_num(now, nan=-1.0) + NCC_GAIN))
    moved &= mean_shift_mm(ref, poses, best_pose, moved) >= MIN_MOVE_MM
    poses[moved] = best_pose[moved]
    return moved


def mean_shift_mm(slices: SliceSet, a: NDArray, b: NDArray, which: NDArray) -> NDArray[np.float64]:
    """``[n]`` how far the pixels of each slice of ``which`` lie apart under poses ``a`` and ``b``
    (their mean distance, mm; 0 elsewhere)."""
    pixels = np.flatnonzero(which[slices.slice_id])
    d = np.linalg.norm(slices.positions(a, pixels) - slices.positions(b, pixels), axis=1)
    sid = slices.slice_id[pixels]
    return np.bincount(sid, d, slices.n_slices) / np.maximum(np.bincount(sid, minlength=slices.n_slices), 1)


def neighbour_starts(poses: NDArray, inside: NDArray, candidates: NDArray, stack_index: NDArray,
                     times: NDArray) -> list[NDArray[np.float64]]:
    """Two ``[n, 4, 4]`` starts: each candidate slice at the pose of the placed slice of its stack
    acquired last before it and first after it, within :data:`START_REACH` acquisitions (NaN where none)."""
    starts = [np.full_like(poses, np.nan), np.full_like(poses, np.nan)]
    for k in np.flatnonzero(candidates & np.isfinite(times)):
        for start, j in zip(starts, acquired_next(inside, stack_index, times, int(k), START_REACH)):
            if j is not None:
                start[k] = poses[j]
    return starts


def acquired_next(inside: NDArray, stack_index: NDArray, times: NDArray, k: int,
                  reach: float) -> tuple[int | None, int | None]:
    """The slices of ``inside`` in slice ``k``'s stack acquired last before it and first after it,
    within ``reach`` acquisitions of it (None where there is none).

    Example:
        >>> acquired_next(np.array([True, False, True, True]), np.zeros(4, int), np.arange(4.0), 1, 2)
        (0, 2)
    """
    same = np.flatnonzero(inside & (stack_index == stack_index[k]) & (np.abs(times - times[k]) <= reach))
    before, after = same[times[same] < times[k]], same[times[same] > times[k]]
    return (int(before[np.argmax(times[before])]) if len(before) else None,
            int(after[np.argmin(times[after])]) if len(after) else None)


def beside_a_jump(slices: SliceSet, frames: NDArray, poses: NDArray, inside: NDArray, candidates: NDArray,
                  times: NDArray, distance_mm: NDArray, expected_error_mm: NDArray) -> dict[int, int]:
    """``{left-out slice: placed slice}``: the left-out slices beside a sudden move that take the pose
    of the placed slice acquired next to them on their side of it (``frames``: the slices'
    :func:`~service.reconstruction.stack_rigid.frame_from_scanner`).

    Only in a stack whose motion is smooth but for its jumps (the model predicts at least
    :data:`SMOOTH_SHARE` of its placed slices within :data:`SMOOTH_MM`; under independent motion
    no neighbour tells where a slice was). The placed slices acquired just before and just after
    the left-out one (within :data:`REACH`) lie on either side of the jump; the slice's own
    predicted pose picks a side where it lies within its expected error of that side's neighbour
    and under :data:`SIDE_RATIO` times its distance to the other side's. A stack is nearly one rigid
    body from one acquisition to the next, so the slice takes that neighbour's ``atlas_from_voxel``.
    """
    stacks = slices.stack_index
    smooth = (np.bincount(stacks, inside & (distance_mm <= SMOOTH_MM), minlength=stacks.max() + 1)
              >= SMOOTH_SHARE * np.bincount(stacks, inside, minlength=stacks.max() + 1))
    out: dict[int, int] = {}
    for k in np.flatnonzero(candidates & smooth[stacks]):
        sides = [j for j in acquired_next(inside, stacks, times, int(k), REACH) if j is not None]
        if not sides:
            continue
        to_frame = np.linalg.inv(slices.stack_affine[k]) @ np.linalg.inv(frames[k])
        own = (poses[k] @ to_frame)[None]
        d = np.array([ed(own, (poses[j] @ to_frame)[None])[0] for j in sides])
        i = int(np.argmin(d))
        if d[i] <= expected_error_mm[k] and (len(d) == 1 or d[i] < SIDE_RATIO * d.max()):
            out[int(k)] = int(sides[i])
    return out
