"""The coarse steps before slice-to-volume registration: stack rigid fit, stack registration, slice start.

::

    fit      = fit_stack_rigid(predicted poses)              per stack one atlas_from_scanner; twin
                                                             branch and inlier flag per slice
    branch   = predicted poses, twins flipped to their stack's branch
    stacks   = register_stacks(fit, outliers left out,       4 -> 2 -> 1 mm, stack to stack; each stack
                   slice_poses=fit.motion_poses)             a rigid body of its slices where the stage's
                                                             motion model puts them, not its file's grid
    delta_s  = stacks_s @ inverse(fit_s)                     what registration moved stack s by
    start_i  = the better, by NCC with the average of the OTHER stacks at the finest level, of
               delta_s @ branch_i   (the slice's own pose, carried along with its stack) and
               stacks_s @ stack_affine_i   (the stack's rigid pose)

A slice's own predicted pose keeps the motion of the fetus between slices, when the network got
it; the stack's pose is better when the prediction is noisy or wrong. Comparing both against the
other stacks (a slice's own stack would favour the stack pose it was averaged at) lets each slice
take the better one; the slice-level registration then starts within its capture range.

The stacks move as bodies of their slices where the stage's motion model puts them (its posterior
mean: the motion it found, not each prediction's noise; the rigid stack where it found none): a
stack's file grid is a distorted image of the brain when the fetus moved during it
(``model_export/experiments/refine_bench.py`` measures a job's refined poses; docs/reconstruction.md).

Example:
    >>> choose_by_ncc(np.array([[0.5, 0.9], [0.8, 0.2]]), np.array([True, True])).tolist()
    [1, 0]
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.consistency.slice_order import SliceOrder
from service.reconstruction.gaussian_average import gaussian_average
from service.reconstruction.grid import bounds_of, make_grid
from service.reconstruction.registration import _Objective
from service.reconstruction.slices import SliceSet
from service.reconstruction.stack_registration import DEFAULT_LEVELS_MM, register_stacks
from service.reconstruction.stack_rigid import StackFit, fit_stack_rigid

START_OWN, START_STACK = 0, 1


@dataclass
class CoarseAlignment:
    """Output of :func:`coarse_align`.

    Attributes:
        poses: ``[n, 4, 4]`` starting transforms of the slice-level registration.
        branch_poses: ``[n, 4, 4]`` the input poses with twins flipped to their stack's branch (the
            frame reference: the predictions' errors average out in it).
        fit: the :class:`~service.reconstruction.stack_rigid.StackFit`.
        atlas_from_scanner: ``[n_stacks, 4, 4]`` after stack registration.
        start: ``[n]`` int, which candidate each slice starts from (``START_OWN`` / ``START_STACK``).
        candidate_ncc: ``[2, n]`` NCC of the two candidates (NaN where not evaluated).
        stack_poses: ``[n, 4, 4]`` each slice at its registered stack's transform (the restart pose
            of a slice whose own pose turns out not to fit).
    """

    poses: NDArray[np.float64]
    branch_poses: NDArray[np.float64]
    fit: StackFit
    atlas_from_scanner: NDArray[np.float64]
    start: NDArray[np.int64]
    candidate_ncc: NDArray[np.float64]
    stack_poses: NDArray[np.float64]


def choose_by_ncc(ncc: NDArray, evaluated: NDArray) -> NDArray[np.int64]:
    """Per slice, the index of the candidate (rows of ``ncc [k, n]``) with the highest NCC (0 where none)."""
    scores = np.where(np.isfinite(ncc), ncc, -np.inf)
    return np.where(evaluated, np.argmax(scores, axis=0), 0).astype(np.int64)


def candidate_ncc(slices: SliceSet, candidates: NDArray, stack_poses: NDArray, resolution_mm: float,
                  subsample: int = 2, margin_mm: float = 5.0) -> NDArray[np.float64]:
    """NCC ``[k, n]`` of each slice at each candidate pose with the average of the other stacks.

    Args:
        slices: the slices.
        candidates: ``[k, n, 4, 4]`` candidate transforms.
        stack_poses: ``[n, 4, 4]`` the transforms the templates (Gaussian averages) are built from.
        resolution_mm: template resolution.
        subsample: every n-th pixel of each slice is compared.
        margin_mm: field-of-view margin of the templates.
    """
    k, n = candidates.shape[:2]
    out = np.full((k, n), np.nan)
    grid = make_grid(resolution_mm, bounds_of(slices.positions(stack_poses), margin_mm))
    stack_of_pixel = slices.stack_index[slices.slice_id]
    pixels = np.arange(0, slices.n_pixels, max(int(subsample), 1))
    for s in np.unique(slices.stack_index[slices.include]):     # a loop over the few stacks
        others = (stack_of_pixel != s).astype(np.float32)
        if not others.any():
            continue
        template = gaussian_average(slices, stack_poses, grid, sigma_mm=resolution_mm, pixel_weight=others).volume
        which = slices.include & (slices.stack_index == s)
        objective = _Objective(template, grid, slices, pixels[which[slices.slice_id[pixels]]], 3, 0.0)
        for c in range(k):
            out[c, which] = objective(candidates[c], which)[0][which]
    return out


def _bodies(slices: SliceSet, fit: StackFit, follow_motion_mm: float) -> NDArray[np.float64] | None:
    """Per slice, where its stack's body puts it: the motion model's pose in stacks that moved by more
    than ``follow_motion_mm``, the rigid stack's elsewhere (``None``: every stack as its file's grid)."""
    if fit.motion_poses is None or fit.motion_mm is None:
        return None
    follow = fit.motion_mm > follow_motion_mm
    if not follow.any():
        return None
    return np.where(follow[slices.stack_index][:, None, None], fit.motion_poses, fit.stack_poses(slices))


def coarse_align(slices: SliceSet, poses: NDArray | None = None, *, plane_x_mm: float | None = None,
                 levels_mm: tuple[float, ...] = DEFAULT_LEVELS_MM, sweeps: int = 2,
                 stage: Callable[[str], None] | None = None, follow_motion_mm: float = 0.0,
                 orders: Sequence[SliceOrder] | None = None) -> CoarseAlignment:
    """Stack rigid fit, stack-to-stack registration and each slice's starting pose (module docstring).

    Args:
        slices: the slices.
        poses: ``[n, 4, 4]`` predicted transforms (default: the slice set's).
        plane_x_mm: atlas mid-sagittal plane for the twin branch choice (``None``: no twins).
        levels_mm: stack registration levels, coarse to fine.
        sweeps: stack registration sweeps per level.
        stage: ``stage(name)`` called at the start of each step (progress and cancellation).
        follow_motion_mm: register a stack as a body of its slices at the stage's motion model
            where that model moves them by more than this from the rigid stack (RMS E.D.; 0: every
            stack the model found motion in; ``inf``: none), else as its file's grid.
        orders: per stack, what is known of its acquisition order (default: the stage chooses).

    Returns:
        The :class:`CoarseAlignment`.
    """
    def step(name: str) -> None:
        if stage is not None:
            stage(name)

    start_poses = np.array(slices.atlas_from_voxel if poses is None else poses, dtype=np.float64)
    step("stack consistency")
    fit = fit_stack_rigid(slices, start_poses, plane_x_mm=plane_x_mm, orders=orders)
    branch = fit.branch_poses(slices, start_poses, 0.0 if plane_x_mm is None else plane_x_mm)
    step("stack registration")
    weight = fit.inlier[slices.slice_id].astype(np.float32)
    reg = register_stacks(slices, fit.atlas_from_scanner, pixel_weight=weight, levels_mm=levels_mm, sweeps=sweeps,
                          slice_poses=_bodies(slices, fit, follow_motion_mm))
    g = reg.atlas_from_scanner
    delta = g @ np.linalg.inv(fit.atlas_from_scanner)
    stack_poses = g[slices.stack_index] @ slices.stack_affine
    own = delta[slices.stack_index] @ branch
    step("slice starting poses")
    candidates = np.stack([own, stack_poses])
    ncc = candidate_ncc(slices, candidates, stack_poses, float(min(levels_mm)))
    start = choose_by_ncc(ncc, slices.include & np.isfinite(ncc).all(axis=0))
    chosen = np.where((start == START_STACK)[:, None, None], stack_poses, own)
    return CoarseAlignment(chosen, branch, fit, g, start, ncc, stack_poses)
