"""Stack-to-stack volumetric rigid registration, multi-resolution (4 -> 2 -> 1 mm).

Each stack moves as one rigid body ``atlas_from_scanner`` (its slices at
``atlas_from_scanner @ stack_affine``). The batched slice registration
(:func:`~service.reconstruction.registration.register_slices`) does the work unchanged: a stack is
presented to it as a single "slice" whose pixels are all the stack's (subsampled) pixels, in the
stack's own voxel indices (:func:`stacks_as_bodies`), so the NCC, its analytic derivatives, the
through-plane PSF and the trust-region steps are those of the slice level.

At every level ``r`` (mm) and sweep, each stack is registered to the Gaussian average (at ``r``) of
the *other* stacks -- its own imprint would hold it in place -- with a trust radius of ``r`` mm /
``r`` degrees; all stacks move at once (Jacobi), then
:func:`~service.reconstruction.registration.anchor_frame` removes their common drift relative to the
starting transforms (the frame stays the one of the predicted poses).

Example:
    >>> import numpy as np
    >>> from service.io.volume import Volume
    >>> vol = Volume(np.ones((6, 6, 4), np.float32), np.diag([1.0, 1.0, 3.0, 1.0]))
    >>> ss = SliceSet.from_stacks([(vol, None, np.repeat(vol.affine[None], 4, 0), np.ones(4, bool))] * 2)
    >>> bodies = stacks_as_bodies(ss, np.repeat(np.eye(4)[None], 2, 0))
    >>> bodies.n_slices, bodies.n_pixels, int(bodies.slice_id.max())
    (2, 288, 1)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.reconstruction.gaussian_average import gaussian_average
from service.reconstruction.grid import bounds_of, make_grid
from service.reconstruction.registration import anchor_frame, register_slices
from service.reconstruction.slices import SliceSet

DEFAULT_LEVELS_MM = (4.0, 2.0, 1.0)
MAX_BODY_PIXELS = 60_000
"""Pixels kept per registration of all stacks (subsampled evenly): a stack's NCC needs few."""


@dataclass
class StackRegistrationResult:
    """Output of :func:`register_stacks`.

    Attributes:
        atlas_from_scanner: ``[n_stacks, 4, 4]`` registered transforms.
        ncc: ``[n_stacks]`` NCC of each stack with the average of the others at the finest level.
        history: per (level, sweep): the mean pixel displacement (mm) of the stacks in that sweep.
    """

    atlas_from_scanner: NDArray[np.float64]
    ncc: NDArray[np.float64]
    history: list[tuple[float, float]] = field(default_factory=list)


def stacks_as_bodies(slices: SliceSet, atlas_from_scanner: ArrayLike, pixel_weight: ArrayLike | None = None,
                     max_pixels: int | None = MAX_BODY_PIXELS,
                     slice_poses: ArrayLike | None = None) -> SliceSet:
    """A :class:`SliceSet` with one "slice" per stack, its pose ``atlas_from_scanner[s] @ stack_affine``.

    Args:
        slices: the slices.
        atlas_from_scanner: ``[n_stacks, 4, 4]``.
        pixel_weight: optional ``[N]``; pixels of weight 0 are left out (e.g. outlier slices).
        max_pixels: keep every k-th pixel so that at most about this many remain (``None``: all).
        slice_poses: optional ``[n, 4, 4]`` per-slice transforms that hold the motion within each
            stack (e.g. the stack-consistency stage's): each pixel's body coordinates are then those
            that put it, at the body's starting pose, where its slice's transform puts it, so the
            stack moves as a rigid body *with* its slices' motion rather than as the file's grid.
    """
    g = np.asarray(atlas_from_scanner, dtype=np.float64)
    n_stacks = len(g)
    keep = np.ones(slices.n_pixels, bool) if pixel_weight is None else np.asarray(pixel_weight) > 0
    pix = np.flatnonzero(keep)
    if max_pixels and len(pix) > max_pixels:
        pix = pix[:: int(np.ceil(len(pix) / max_pixels))]
    stack_of_pixel = slices.stack_index[slices.slice_id[pix]]
    order = np.argsort(stack_of_pixel, kind="stable")
    pix, sid = pix[order], stack_of_pixel[order].astype(np.int32)
    first = np.array([int(np.flatnonzero(slices.stack_index == s)[0]) for s in range(n_stacks)])
    saff = slices.stack_affine[first]
    has = np.bincount(sid, minlength=n_stacks) > 0
    voxel = slices.voxel[pix]
    if slice_poses is not None:        # body coordinates: inverse(body pose) @ slice pose @ voxel
        body = np.linalg.inv(g @ saff)
        moved = slices.positions(np.asarray(slice_poses, np.float64), pix)
        b = body[sid]
        voxel = (np.einsum("nij,nj->ni", b[:, :3, :3], moved) + b[:, :3, 3]).astype(np.float32)
    return SliceSet(values=slices.values[pix], voxel=voxel, slice_id=sid, atlas_from_voxel=g @ saff,
                    thickness_mm=slices.thickness_mm[first], pixel_mm=slices.pixel_mm[first],
                    slice_axis=slices.slice_axis[first], stack_index=np.arange(n_stacks),
                    slice_index=np.zeros(n_stacks, np.int64), stack_affine=saff, include=has)


def register_stacks(slices: SliceSet, atlas_from_scanner: ArrayLike, *, pixel_weight: ArrayLike | None = None,
                    levels_mm: tuple[float, ...] = DEFAULT_LEVELS_MM, sweeps: int = 2, margin_mm: float = 10.0,
                    max_iterations: int = 30, cancel: Callable[[], None] | None = None,
                    slice_poses: ArrayLike | None = None) -> StackRegistrationResult:
    """Rigidly register the stacks to each other, coarse to fine (see the module docstring).

    Args:
        slices: the slices.
        atlas_from_scanner: ``[n_stacks, 4, 4]`` starting transforms (e.g. :func:`fit_stack_rigid`).
        pixel_weight: optional ``[N]`` (0: leave the pixel out, e.g. slices inconsistent with their stack).
        levels_mm: template resolutions, coarse to fine; also the trust radius (mm == degrees) at each.
        sweeps: Jacobi sweeps per level.
        margin_mm: field-of-view margin of the templates.
        max_iterations: iteration bound of each registration.
        cancel: called between registrations (may raise to stop).
        slice_poses: optional ``[n, 4, 4]`` slice transforms carrying each stack's motion
            (:func:`stacks_as_bodies`); the result still maps each stack's rigid frame, so that
            ``result[s] @ inverse(atlas_from_scanner[s])`` moves its slices' transforms.

    Returns:
        The :class:`StackRegistrationResult` (a single stack is returned unchanged, NCC NaN).
    """
    start = np.array(atlas_from_scanner, dtype=np.float64)
    bodies = stacks_as_bodies(slices, start, pixel_weight, slice_poses=slice_poses)
    n_stacks = bodies.n_slices
    ncc = np.full(n_stacks, np.nan)
    if int(bodies.include.sum()) < 2:
        return StackRegistrationResult(start, ncc)
    poses = bodies.atlas_from_voxel.copy()
    reference = poses.copy()
    stack_of_pixel = bodies.slice_id
    history = []
    for level in levels_mm:
        for _ in range(max(int(sweeps), 1)):
            grid = make_grid(level, bounds_of(bodies.positions(poses), margin_mm))
            moved = poses.copy()
            for s in np.flatnonzero(bodies.include):          # a loop over the few stacks
                if cancel is not None:
                    cancel()
                others = (stack_of_pixel != s).astype(np.float32)
                template = gaussian_average(bodies, poses, grid, sigma_mm=level, pixel_weight=others).volume
                active = np.arange(n_stacks) == s
                res = register_slices(template, grid, bodies, poses, active=active, subsample=1, psf_points=3,
                                      max_iterations=max_iterations, step_mm=level, min_step_mm=0.05 * level,
                                      max_pixels=None)
                moved[s] = res.atlas_from_voxel[s]
                ncc[s] = res.ncc[s]
            moved = anchor_frame(bodies, reference, moved)
            shift = np.linalg.norm(bodies.positions(moved) - bodies.positions(poses), axis=1).mean()
            history.append((float(level), float(shift)))
            poses = moved
    return StackRegistrationResult(poses @ np.linalg.inv(bodies.stack_affine), ncc, history)
