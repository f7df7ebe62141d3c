"""One rigid ``atlas_from_scanner`` per stack from its slices' predicted poses (robust, twin-aware).

Within a stack the slices were acquired in one scanner frame, so (apart from the fetus' motion
between slices) every slice's pose implies the same rigid ``atlas_from_scanner``::

    X_i = atlas_from_voxel_i @ inverse(stack_affine)          (atlas mm <- scanner mm)

A network's poses scatter around it, a few are gross errors, and some sit on the left-right twin
branch (:mod:`service.geometry.twin`). For the twin of slice ``i`` the implied transform is
``M @ atlas_from_voxel_i @ Refl_i @ inverse(stack_affine)`` with ``Refl_i`` the reflection of the
slice axis about the slice's own index (``twin(T) = M T diag(1, 1, -1, 1)`` written in voxel indices,
see :func:`twin_atlas_from_voxel`): the twins of different slices of one stack do not agree with each
other (their implied positions run the other way along the normal), so the branch of each slice is
decidable against the consensus of the stack.

Estimate, per stack (a loop over stacks; everything within a stack is batched):

1. the medoid of all candidates (each slice and, twin-aware, its twin) under the truncated distance
   ``d^2 = |X_a(c) - X_b(c)|^2 + (r angle(R_a^T R_b))^2`` (``c``: the stack's centre in scanner mm,
   ``r = RADIUS_MM``: 1 degree weighs as the displacement it causes at the rim of a fetal brain);
2. iterated: each slice takes the branch nearer to the estimate; inliers are the slices within
   ``K_MAD`` robust standard deviations (and at least ``MIN_INLIER_MM``); the estimate is the Fréchet
   mean (:func:`service.geometry.se3.frechet_mean`) of the inliers, taken about ``c``.

This is the reconstruction's seam for the stack-consistency stage of ``/v1/predict``: when that
lands, :func:`fit_stack_rigid` delegates to it and keeps this signature.

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

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.geometry import se3
from service.geometry.pose import apply, make_pose, translate
from service.geometry.twin import mirror
from service.reconstruction.slices import SliceSet

RADIUS_MM = 40.0
"""Rotation weight of the candidate distance: mm of displacement per radian."""
K_MAD = 3.0
MIN_INLIER_MM = 6.0
"""Slices within this distance of the stack's estimate are always inliers (predictions are never exact)."""
TRUNCATE_MM = 30.0
IRLS_ITERATIONS = 5


@dataclass
class StackFit:
    """Output of :func:`fit_stack_rigid`.

    Attributes:
        atlas_from_scanner: ``[n_stacks, 4, 4]`` one rigid transform per stack (identity where a
            stack has no usable slice).
        twin: ``[n]`` bool, slices whose pose lies on the twin branch of the stack's consensus.
        inlier: ``[n]`` bool, slices (on their chosen branch) consistent with the stack's transform.
        distance_mm: ``[n]`` each slice's distance (chosen branch) from its stack's transform (NaN:
            not used).
    """

    atlas_from_scanner: NDArray[np.float64]
    twin: NDArray[np.bool_]
    inlier: NDArray[np.bool_]
    distance_mm: NDArray[np.float64]

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


def _distance(rot_a: NDArray, p_a: NDArray, rot_b: NDArray, p_b: NDArray) -> NDArray:
    """Candidate distance (mm), broadcasting over leading axes."""
    w = se3.so3_log(np.swapaxes(rot_a, -1, -2) @ rot_b)
    return np.sqrt(np.sum((p_a - p_b) ** 2, -1) + RADIUS_MM**2 * np.sum(w * w, -1))


def _fit_one(x: NDArray, xt: NDArray | None, centre: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Robust transform of one stack from its slices' candidates ``x`` and twins ``xt`` ``[m, 4, 4]``."""
    about = translate(centre)
    cands = x[None] if xt is None else np.stack([x, xt])                      # [b, m, 4, 4]
    rot, pos = cands[..., :3, :3], apply(cands, centre)
    flat_r, flat_p = rot.reshape(-1, 3, 3), pos.reshape(-1, 3)
    pair = _distance(flat_r[:, None, None], flat_p[:, None, None], rot[None], pos[None])   # [bm, b, m]
    score = np.minimum(pair.min(axis=1), TRUNCATE_MM).sum(axis=1)
    est = cands.reshape(-1, 4, 4)[int(np.argmin(score))]
    use_twin = np.zeros(len(x), bool)
    for _ in range(IRLS_ITERATIONS):
        d = _distance(est[None, None, :3, :3], apply(est, centre)[None, None], rot, pos)   # [b, m]
        use_twin = d.argmin(axis=0) == 1 if xt is not None else use_twin
        dist = d.min(axis=0)
        scale = se3.MAD_SCALE * float(np.median(dist))
        inlier = dist <= max(K_MAD * scale, MIN_INLIER_MM)
        chosen = np.where(use_twin[:, None, None], cands[-1], cands[0])
        est = se3.frechet_mean(chosen[inlier] @ about) @ se3.inverse(about)
    d = _distance(est[None, None, :3, :3], apply(est, centre)[None, None], rot, pos)
    use_twin = d.argmin(axis=0) == 1 if xt is not None else use_twin
    dist = d.min(axis=0)
    scale = se3.MAD_SCALE * float(np.median(dist))
    return est, use_twin, dist <= max(K_MAD * scale, MIN_INLIER_MM), dist


def fit_stack_rigid(slices: SliceSet, atlas_from_voxel: ArrayLike | None = None, *,
                    plane_x_mm: float | None = None, use: ArrayLike | None = None) -> StackFit:
    """Robust per-stack ``atlas_from_scanner`` from per-slice poses (see the module docstring).

    Args:
        slices: the slice set (stack affines, slice axes and indices).
        atlas_from_voxel: ``[n, 4, 4]`` per-slice poses (default: the slice set's own).
        plane_x_mm: the atlas mid-sagittal plane; ``None``: the poses have no twin (no branch choice).
        use: ``[n]`` bool, the slices to fit from (default: the included ones).

    Returns:
        The :class:`StackFit`.
    """
    poses = np.asarray(slices.atlas_from_voxel if atlas_from_voxel is None else atlas_from_voxel, np.float64)
    use = slices.include.copy() if use is None else np.asarray(use, bool) & slices.include
    n, n_stacks = slices.n_slices, int(slices.stack_index.max()) + 1
    x_all = poses @ np.linalg.inv(slices.stack_affine)
    xt_all = None
    if plane_x_mm is not None:
        xt_all = twin_atlas_from_voxel(poses, slices.slice_axis, slices.slice_index, plane_x_mm)
        xt_all = xt_all @ np.linalg.inv(slices.stack_affine)
    centres_vox = slices.centres(slices.stack_affine)                    # scanner mm of each slice centre
    out = np.repeat(np.eye(4)[None], n_stacks, axis=0)
    twin = np.zeros(n, bool)
    inlier = np.zeros(n, bool)
    dist = np.full(n, np.nan)
    for s in range(n_stacks):                   # a loop over the few stacks; slices are batched
        idx = np.flatnonzero(use & (slices.stack_index == s))
        if idx.size == 0:
            continue
        centre = centres_vox[idx].mean(axis=0)
        est, tw, inl, d = _fit_one(x_all[idx], None if xt_all is None else xt_all[idx], centre)
        out[s] = make_pose(est[:3, :3], est[:3, 3])
        twin[idx], inlier[idx], dist[idx] = tw, inl, d
    return StackFit(out, twin, inlier, dist)
