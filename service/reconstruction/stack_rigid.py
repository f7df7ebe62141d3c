"""One rigid ``atlas_from_scanner`` per stack from its slices' predicted poses (robust, twin-aware).

The work is the stack-consistency stage of ``/v1/predict``
(:func:`service.consistency.stack_fit.fit_stack`: twin branch by RANSAC, Tukey IRLS rigid fit,
leave-one-out motion model, fusion, inconsistent slices); this module only expresses the
reconstruction's slices in its terms. A slice's transform ``A_k`` (voxel -> atlas) is written as a
pose ``P_k`` of a frame centred on the slice (its plane ``z = 0``, axes those of the stack), so that
``A_k = P_k @ N_k @ stack_affine`` with ``N_k`` the rigid frame <- scanner map, the stage's
``network_from_scanner``. The twin of ``A_k`` in voxel indices is ``M @ A_k @ Refl_k``
(:func:`twin_atlas_from_voxel`, ``Refl_k`` mirrors the slice axis about the slice's own index).

Where the stage finds a stack undecidable (its slices do not agree), the stack's transform is the
Fréchet mean of its slices' and no slice is flagged twin or inlier.

Example:
    >>> import numpy as np
    >>> from service.reconstruction.slices import SliceSet
    >>> from service.io.volume import Volume
    >>> vol = Volume(np.ones((6, 6, 4), np.float32), np.diag([1.0, 1.0, 3.0, 1.0]))
    >>> shift = np.eye(4); shift[0, 3] = 5.0
    >>> ss = SliceSet.from_stacks([(vol, None, np.repeat((shift @ vol.affine)[None], 4, 0), np.ones(4, bool))])
    >>> fit = fit_stack_rigid(ss, ss.atlas_from_voxel)
    >>> fit.atlas_from_scanner[0, :3, 3].round(6).tolist(), fit.inlier.tolist()
    ([5.0, 0.0, 0.0], [True, True, True, True])
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.consistency.motion_model import ERROR_CORRELATIONS
from service.consistency.slice_order import SliceOrder
from service.consistency.stack_fit import fit_stack
from service.geometry import se3
from service.geometry.anchors import ed
from service.geometry.pose import make_pose, translate
from service.geometry.twin import DEFAULT_PLANE_X_MM, mirror
from service.reconstruction.slices import SliceSet

@dataclass
class StackFit:
    """Output of :func:`fit_stack_rigid`.

    Attributes:
        atlas_from_scanner: ``[n_stacks, 4, 4]`` one rigid transform per stack (identity where a
            stack has no usable slice).
        twin: ``[n]`` bool, slices whose pose lies on the twin branch of the stack's consensus.
        inlier: ``[n]`` bool, slices (on their chosen branch) consistent with the stack's transform.
        distance_mm: ``[n]`` E.D. (mm) of each slice's pose (its branch) from the stack's motion model
            (NaN: stack undecidable or no slice used).
        motion_poses: ``[n, 4, 4]`` each slice's transform under its stack's motion model (the
            stage's posterior mean: the motion it found, without the network's per-slice noise);
            the stack's rigid transform where the stack is undecidable, has no usable slice, or
            put slices on the twin branch while ``plane_x_mm`` is ``None`` (``None``: not computed).
        motion_mm: ``[n_stacks]`` how far the motion model moves each stack's slices from its rigid
            transform (RMS E.D. over the slices it was fitted from; 0 where it found none).
        times: ``[n]`` each slice's acquisition time under the order the stage chose for its stack
            (NaN where the stack is undecidable or has no usable slice).
    """

    atlas_from_scanner: NDArray[np.float64]
    twin: NDArray[np.bool_]
    inlier: NDArray[np.bool_]
    distance_mm: NDArray[np.float64]
    motion_poses: NDArray[np.float64] | None = None
    motion_mm: NDArray[np.float64] | None = None
    times: NDArray[np.float64] | None = None

    def branch_poses(self, slices: SliceSet, atlas_from_voxel: ArrayLike, plane_x_mm: float) -> NDArray[np.float64]:
        """``atlas_from_voxel`` with the twin-branch slices replaced by their twins (the stack's branch)."""
        poses = np.array(atlas_from_voxel, dtype=np.float64)
        poses[self.twin] = twin_atlas_from_voxel(poses[self.twin], slices.slice_axis[self.twin],
                                                 slices.slice_index[self.twin], plane_x_mm)
        return poses

    def stack_poses(self, slices: SliceSet) -> NDArray[np.float64]:
        """``[n, 4, 4]`` every slice at its stack's rigid transform: ``atlas_from_scanner @ stack_affine``."""
        return self.atlas_from_scanner[slices.stack_index] @ slices.stack_affine


def twin_atlas_from_voxel(atlas_from_voxel: ArrayLike, slice_axis: ArrayLike, slice_index: ArrayLike,
                          plane_x_mm: float) -> NDArray[np.float64]:
    """Twin ``[n, 4, 4]`` of slice transforms: ``M @ A @ Refl`` (``Refl``: slice axis mirrored about the slice).

    ``twin(T) = M T diag(1, 1, -1, 1)`` on the slice-frame pose ``T``; with ``A = T S`` and the slice
    frame's ``z = +-spacing (k - slice_index)`` (:func:`service.preprocess.stack.split_stack`),
    ``diag(1, 1, -1, 1) S = S Refl``, so the twin of ``A`` is ``M A Refl`` whatever ``S`` is.
    """
    a = np.asarray(atlas_from_voxel, dtype=np.float64)
    n = len(a)
    refl = np.repeat(np.eye(4)[None], n, axis=0)
    axis = np.asarray(slice_axis, dtype=np.int64)
    rows = np.arange(n)
    refl[rows, axis, axis] = -1.0
    refl[rows, axis, 3] = 2.0 * np.asarray(slice_index, dtype=np.float64)
    return mirror(plane_x_mm) @ a @ refl


def frame_from_scanner(slices: SliceSet) -> NDArray[np.float64]:
    """``[n, 4, 4]`` rigid scanner -> slice frame maps: origin at the slice's pixel centre, ``z`` its normal.

    The axes are the stack's in-plane voxel axes and the slice axis (unit length, the normal's sign
    making the frame right-handed), so the slice's own plane is ``z = 0`` as the twin requires. A
    slice without pixels (left out of the volume) has its origin on its own plane too, where the
    centre of its stack's pixels projects onto it: its twin is mirrored about its own plane and its
    lever arm is its distance from the stack's middle, as for the slices with pixels.
    """
    n = slices.n_slices
    cols = slices.stack_affine[:, :3, :3] / np.linalg.norm(slices.stack_affine[:, :3, :3], axis=1, keepdims=True)
    axis = slices.slice_axis
    p = np.where(axis == 0, 1, 0)
    q = np.where(axis == 2, 1, 2)
    rows = np.arange(n)
    rot = np.stack([cols[rows, :, p], cols[rows, :, q], cols[rows, :, axis]], axis=-1)
    rot[..., 2] *= np.sign(np.linalg.det(rot))[:, None]
    centre = slices.centres(slices.stack_affine)
    counts = slices.pixel_counts()
    empty = counts == 0
    if empty.any():                                 # slices without pixels: on their own plane, nearest the stack's pixels
        seen = np.bincount(slices.stack_index, counts, minlength=slices.stack_index.max() + 1)
        middle = np.stack([np.bincount(slices.stack_index, centre[:, d] * counts, minlength=len(seen))
                           for d in range(3)], -1) / np.maximum(seen, 1)[:, None]
        unseen = seen[slices.stack_index] == 0      # a stack without pixels: its voxel origin, moved onto the plane
        middle = np.where(unseen[:, None], slices.stack_affine[:, :3, 3], middle[slices.stack_index])
        on_plane = slices.stack_affine[rows, :3, axis] * slices.slice_index[:, None] + slices.stack_affine[:, :3, 3]
        normal = rot[..., 2]
        off = np.einsum("nd,nd->n", middle - on_plane, normal)
        centre[empty] = (middle - off[:, None] * normal)[empty]
    return se3.inverse(make_pose(rot, centre))


def fit_stack_rigid(slices: SliceSet, atlas_from_voxel: ArrayLike | None = None, *,
                    plane_x_mm: float | None = None, use: ArrayLike | None = None,
                    orders: Sequence[SliceOrder] | None = None, expected_error_mm: ArrayLike | None = None,
                    error_correlations: tuple[float, ...] = ERROR_CORRELATIONS,
                    frames: NDArray | None = None) -> StackFit:
    """Per-stack ``atlas_from_scanner`` from per-slice poses by the stack-consistency stage (module docstring).

    Args:
        slices: the slice set (stack affines, slice axes and indices).
        atlas_from_voxel: ``[n, 4, 4]`` per-slice poses (default: the slice set's own).
        plane_x_mm: the atlas mid-sagittal plane; ``None``: the poses have no twin (the stage still
            runs with the default plane, but no slice is flipped).
        use: ``[n]`` bool, the slices to fit from (default: the included ones).
        orders: per stack, what is known of its acquisition order (default: the stage chooses).
        expected_error_mm: ``[n]`` each pose's expected E.D. (the stage weighs the slices by it; NaN:
            unknown); default: the stage estimates one error for all from acquisition neighbours.
        error_correlations: how alike neighbouring slices' errors may be (:func:`fit_stack`).
        frames: the slices' :func:`frame_from_scanner`, where the caller has them already.

    Returns:
        The :class:`StackFit`.
    """
    poses = np.asarray(slices.atlas_from_voxel if atlas_from_voxel is None else atlas_from_voxel, np.float64)
    use = slices.include.copy() if use is None else np.asarray(use, bool) & slices.include
    n, n_stacks = slices.n_slices, int(slices.stack_index.max()) + 1
    n_k = frame_from_scanner(slices) if frames is None else np.asarray(frames, np.float64)
    x_all = poses @ np.linalg.inv(slices.stack_affine)                   # atlas_from_scanner per slice
    frame_poses = x_all @ se3.inverse(n_k)
    out = np.repeat(np.eye(4)[None], n_stacks, axis=0)
    twin = np.zeros(n, bool)
    inlier = np.zeros(n, bool)
    dist = np.full(n, np.nan)
    motion = np.zeros((n, 4, 4))
    moved = np.zeros(n_stacks)
    times = np.full(n, np.nan)
    errors = None if expected_error_mm is None else np.asarray(expected_error_mm, np.float64)
    for s in range(n_stacks):                   # a loop over the few stacks; slices are batched
        idx = np.flatnonzero(slices.stack_index == s)
        if not use[idx].any():
            motion[idx] = slices.stack_affine[idx]
            continue
        order = (orders[s] if orders is not None else SliceOrder()).times(len(idx))
        fit = fit_stack(frame_poses[idx], n_k[idx], use[idx], DEFAULT_PLANE_X_MM if plane_x_mm is None else plane_x_mm,
                        None if errors is None else errors[idx], times=order, error_correlations=error_correlations)
        if fit.decidable and fit.atlas_from_scanner is not None:
            times[idx] = order[fit.acquisition_order]
            out[s] = fit.atlas_from_scanner
            twin[idx] = fit.twinned & (plane_x_mm is not None)
            inlier[idx] = use[idx] & ~fit.inconsistent
            dist[idx] = fit.residual_mm
            if plane_x_mm is not None or not fit.twinned.any():
                motion[idx] = fit.poses @ n_k[idx] @ slices.stack_affine[idx]
                rigid = fit.atlas_from_scanner @ se3.inverse(n_k[idx])
                used = use[idx]
                moved[s] = float(np.sqrt(np.mean(ed(fit.poses[used], rigid[used]) ** 2)))
                continue
        else:                                   # the mean about the stack's centre, not the scanner's origin
            about = translate(se3.inverse(n_k[idx])[:, :3, 3].mean(axis=0))
            out[s] = se3.frechet_mean(x_all[idx[use[idx]]] @ about) @ se3.inverse(about)
        motion[idx] = out[s] @ slices.stack_affine[idx]
    if plane_x_mm is None and twin.any():
        twin[:] = False
    return StackFit(out, twin, inlier, dist, motion, moved, times)
