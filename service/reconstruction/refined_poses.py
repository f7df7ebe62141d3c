"""Refined slice poses in the ``/v1/predict`` response schema (what SVRTK users get as slice transforms).

A ``/v1/predict`` slice reports the network's mean pose ``T`` (its frame -> atlas mm: ``rotation``,
``rotation_vector``, ``quaternion_wxyz``, ``translation_mm``, ``anchor_points_mm``) and
``atlas_from_voxel = T @ frame_from_voxel``. The reconstruction refines ``atlas_from_voxel`` to
``A'``; the frame does not change, so the refined pose is::

    T' = A' @ inverse(A) @ T          (T' @ frame_from_voxel == A')

and every pose field is recomputed from ``T'``. Where the input body has no pose fields (a client
may upload only ``atlas_from_voxel`` and ``accepted``), the frame is the slice grid's own
(:func:`service.preprocess.stack.split_stack`): ``T' = A' @ inverse(slice_from_voxel)``.

``accepted`` and ``reason`` stay the model's (the body is a valid ``poses`` input to a new job),
as do the other fields of the starting body (``expected_error_mm``, ``geodesic_variance``,
``branch``, ``network_atlas_from_voxel``, each stack's ``consistency``): they describe the starting
prediction, not the refined pose. Fields are added: ``included``, ``exclusion_reason``, ``weight``,
``ncc`` and ``held_out_ncc`` per slice (the refined pose's own agreement with the volume),
``placed_by_stack_motion``, ``placed_by_volume`` and ``refined_expected_error_mm`` (the refined
pose's expected E.D., :mod:`~service.reconstruction.pose_errors`), and ``refined_by`` at the top.

Example:
    >>> import numpy as np
    >>> from service.geometry import se3
    >>> t = se3.exp(np.array([0.1, 0.2, -0.1, 5.0, 0.0, 1.0])); f = np.diag([2.0, 2.0, 3.0, 1.0])
    >>> u = se3.exp(np.array([0.0, 0.0, 0.05, 1.0, -1.0, 0.0]))
    >>> bool(np.allclose(refined_frame_poses(u @ t @ f, t @ f, t[None])[0] @ f, u @ t @ f))
    True
"""

from __future__ import annotations

import copy
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from service.geometry import anchors


def refined_frame_poses(refined: ArrayLike, original: ArrayLike, frame_poses: ArrayLike) -> NDArray[np.float64]:
    """``T' = A' @ inverse(A) @ T`` for ``[n, 4, 4]`` refined / original ``atlas_from_voxel`` and poses ``T``."""
    a_new = np.asarray(refined, dtype=np.float64).reshape(-1, 4, 4)
    a_old = np.asarray(original, dtype=np.float64).reshape(-1, 4, 4)
    return a_new @ np.linalg.inv(a_old) @ np.asarray(frame_poses, dtype=np.float64).reshape(-1, 4, 4)


def _num(v: float) -> float | None:
    return None if v is None or not math.isfinite(float(v)) else float(v)


def pose_fields(poses: ArrayLike) -> list[dict]:
    """The pose fields of the contract for ``[n, 4, 4]`` proper rigid poses (vectorised)."""
    t = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(t) == 0:
        return []
    rot = t[:, :3, :3]
    r = Rotation.from_matrix(rot)
    rotvec, quat = r.as_rotvec(), r.as_quat(canonical=True, scalar_first=True)
    pts = anchors.encode(t).reshape(-1, 3, 3)
    return [{"anchor_points_mm": pts[i].tolist(), "rotation": rot[i].tolist(), "rotation_vector": rotvec[i].tolist(),
             "quaternion_wxyz": quat[i].tolist(), "translation_mm": t[i, :3, 3].tolist()} for i in range(len(t))]


def refined_poses_body(predict_body: dict, refined: ArrayLike, slice_from_voxel: list[NDArray], *,
                       included: ArrayLike, weight: ArrayLike, ncc: ArrayLike, reasons: list[str | None],
                       job_id: str, held_out_ncc: ArrayLike | None = None,
                       placed_by_stack_motion: ArrayLike | None = None,
                       placed_by_volume: ArrayLike | None = None,
                       refined_expected_error_mm: ArrayLike | None = None) -> dict:
    """A ``/v1/predict``-shaped body with the refined poses of every slice.

    Args:
        predict_body: the ``/v1/predict`` body the job started from (uploaded or its own prediction).
        refined: ``[n, 4, 4]`` refined ``atlas_from_voxel`` of all slices, stacks concatenated in order.
        slice_from_voxel: per stack ``[n_s, 4, 4]`` voxel -> slice grid frame (used where the body has
            no pose fields).
        included, weight, ncc, reasons: per slice, from the reconstruction.
        held_out_ncc: per slice, the NCC against the volume made without the slice's stack (None:
            not measured; null per slice).
        placed_by_stack_motion: per slice, left out of the volume and placed by its stack's motion
            through the slices in it (:mod:`~service.reconstruction.left_out`; None: none).
        placed_by_volume: per slice, left out of the volume and registered to it (None: none).
        refined_expected_error_mm: per slice, the refined pose's expected E.D.
            (:mod:`~service.reconstruction.pose_errors`; None: not estimated; null per slice).
        job_id: the job (``refined_by``).

    Returns:
        The new body (the input is not modified).
    """
    body = copy.deepcopy(predict_body)
    a_new = np.asarray(refined, dtype=np.float64)
    inc, w, c = np.asarray(included, bool), np.asarray(weight, np.float64), np.asarray(ncc, np.float64)
    held, refined_error = (np.full(len(c), np.nan) if x is None else np.asarray(x, np.float64)
                           for x in (held_out_ncc, refined_expected_error_mm))
    by_motion, by_volume = (np.zeros(len(c), bool) if flags is None else np.asarray(flags, bool)
                            for flags in (placed_by_stack_motion, placed_by_volume))
    start = 0
    for stack, sfv in zip(body["stacks"], slice_from_voxel):
        slices = stack["slices"]
        n = len(slices)
        sl = slice(start, start + n)
        a_old = np.array([s["atlas_from_voxel"] for s in slices], dtype=np.float64)
        if all("rotation" in s and "translation_mm" in s for s in slices):
            t_old = np.zeros((n, 4, 4))
            t_old[:, :3, :3] = [s["rotation"] for s in slices]
            t_old[:, :3, 3] = [s["translation_mm"] for s in slices]
            t_old[:, 3, 3] = 1.0
            t_new = refined_frame_poses(a_new[sl], a_old, t_old)
        else:
            t_new = a_new[sl] @ np.linalg.inv(np.asarray(sfv, dtype=np.float64))
        for k, (s, fields) in enumerate(zip(slices, pose_fields(t_new))):
            i = start + k
            s.update(fields)
            s["atlas_from_voxel"] = a_new[i].tolist()
            s.update(included=bool(inc[i]), exclusion_reason=reasons[i], weight=_num(w[i]), ncc=_num(c[i]),
                     held_out_ncc=_num(held[i]), placed_by_stack_motion=bool(by_motion[i]),
                     placed_by_volume=bool(by_volume[i]), refined_expected_error_mm=_num(refined_error[i]))
        start += n
    body.setdefault("request_id", job_id)
    body.setdefault("timing_ms", {})
    body["refined_by"] = {"job_id": job_id, "stage": "slice-to-volume reconstruction"}
    return body
