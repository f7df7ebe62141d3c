"""The JSON documents of a prediction: its stacks, their slices and their ``consistency`` reports.

The one place that writes a stack and a slice as the HTTP contract (``docs/api.md``) names them.
``/v1/predict``'s answer, a stream's ``pose`` and ``stack`` messages (``service.streaming.messages``), a
reconstruction job's starting poses and the evaluations all write them here, so that a job worker
or an evaluation needs no request layer to write what ``/v1/predict`` would have answered.

Example:
    >>> stack_report(None) is None                   # the stage was off
    True
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from service.consistency.refined_errors import agreed
from service.consistency.stage import StackPoses
from service.geometry import anchors
from service.io.volume import Volume
from service.pipeline.predict import StackPrediction
from service.preprocess.noise import NOISY_INPUT


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def slice_objects(p: StackPrediction, rows: slice = slice(None)) -> list[dict]:
    """Every slice of one stack, accepted or not, in order; ``rows``: the rows of ``p.prepared``'s
    slices that ``p``'s poses are. ``signal_lost`` is judged against the slice's stack: null where
    ``p.prepared`` holds one slice (a stream's slice before its stack ends)."""
    out, est = p.poses, p.estimate
    mean = out.poses
    atlas_from_voxel = mean @ p.network_from_voxel
    network_atlas_from_voxel = est.mean @ p.network_from_voxel
    rot = mean[:, :3, :3]
    r = Rotation.from_matrix(rot)
    rotvec = r.as_rotvec()
    quat = r.as_quat(canonical=True, scalar_first=True)
    pts = anchors.encode(mean).reshape(-1, 3, 3)
    expected: NDArray = out.expected_error_mm if out.expected_error_mm is not None else np.full(len(mean), np.nan)
    seen = est.estimated
    lost = p.prepared.signal_lost[rows] if len(p.prepared.slices.images) > 1 else [None] * len(mean)
    cut = p.prepared.cut_by_field_of_view[rows]
    return [
        {
            "index": i, "accepted": p.reasons[i] is None, "reason": p.reasons[i],
            "geodesic_variance": _finite(est.variance[i]),
            "anchor_points_mm": pts[i].tolist(), "rotation": rot[i].tolist(), "rotation_vector": rotvec[i].tolist(),
            "quaternion_wxyz": quat[i].tolist(), "translation_mm": mean[i, :3, 3].tolist(),
            "atlas_from_voxel": atlas_from_voxel[i].tolist(),
            "branch": "twin" if out.twinned[i] else "network", "twin_mass": float(out.twin_mass[i]),
            "network_atlas_from_voxel": network_atlas_from_voxel[i].tolist() if seen[i] else None,
            "expected_error_mm": _finite(expected[i]),
            "signal_lost": None if lost[i] is None else bool(lost[i]),
            "cut_by_field_of_view": bool(cut[i]),
        }
        for i in range(len(mean))
    ]


def stack_report(out: StackPoses | None) -> dict | None:
    """A stack's ``consistency`` object: the stage's fit, where pooling put the stack and what image
    consistency did (``None`` when the stage was off)."""
    fit = None if out is None else out.fit
    if fit is None:
        return None
    report = {
        "decidable": bool(fit.decidable),
        "atlas_from_scanner": fit.atlas_from_scanner.tolist() if fit.decidable and fit.atlas_from_scanner is not None else None,
        "inlier_fraction": float(fit.inlier_fraction),
        "twinned_slices": int(fit.twinned.sum()),
        "inconsistent_slices": int(out.inconsistent.sum()),
        "acquisition_order": fit.acquisition_order if fit.decidable else None,
        "motion_bandwidth_slices": _finite(fit.bandwidth) if fit.decidable else None,
        "network_error_mm": _finite(fit.noise_mm),
        "model_error_mm": _finite(fit.model_mm),
        "branch_margin": _finite(fit.branch_margin) if fit.decidable else None,
        "branch_decided": fit.branch_decided,
        "branch_from_request": fit.branch_from_request,
        "branch_agrees_with_request": fit.agrees_with_request,
        "mirrored": fit.mirrored,
        "apart_from_request": out.apart,
        "apart_mm": _finite(round(out.apart_mm, 1)),
    }
    pooled = out.pooled          # the keys always there (None: not pooled), as /v1/predict's schema gives them
    report.update({"pooled_atlas_from_scanner": None if pooled is None else pooled.atlas_from_scanner.tolist(),
                   "stacks_pooled": None if pooled is None else pooled.stacks,
                   "between_stacks_sd_mm": None if pooled is None else pooled.between_stacks_sd_mm})
    ic = out.image_consistency
    report["image_consistency"] = None if ic is None else {
        "stacks": ic.stacks, "pairs": ic.pairs, "slices_refined": ic.slices_refined,
        "median_move_mm": ic.median_move_mm, "mismatch_before": _finite(ic.mismatch_before),
        "mismatch_after": _finite(ic.mismatch_after), "agreed": agreed(ic.mismatch_after),
    }
    return report


def stack_geometry(index: int, filename: str, volume: Volume, slice_axis: int) -> dict:
    """A stack object's place and geometry, as the service read its file: ``index``, ``filename``,
    ``shape``, ``spacing_mm``, ``slice_axis`` and ``scanner_from_voxel`` (voxel index -> scanner RAS mm)."""
    return {"index": index, "filename": filename, "shape": list(volume.array.shape),
            "spacing_mm": [float(x) for x in volume.spacing], "slice_axis": int(slice_axis),
            "scanner_from_voxel": np.asarray(volume.affine, np.float64).tolist()}


def stack_objects(predictions: list[StackPrediction]) -> list[dict]:
    """The response's ``stacks``: each stack's file, geometry (``scanner_from_voxel``: voxel index ->
    scanner RAS mm, as the service read the file), slices, consistency and localisation."""
    stacks = []
    for index, p in enumerate(predictions):
        stacks.append({
            **stack_geometry(index, p.prepared.upload.filename, p.prepared.upload.volume, p.prepared.slices.slice_axis),
            "slices": slice_objects(p), "consistency": stack_report(p.poses),
            "localisation": {**p.prepared.localisation.report(), "region_of_interest": p.prepared.upload.mask_is_region},
            "noise": noise_report(p.prepared.input_noise, p.noise_error_mm),
            "frame": frame_report(p.request_network_error_mm, p.frame_error_mm),
        })
    return stacks


def noise_report(level: float, added_mm: float = 0.0) -> dict:
    """A stack's ``noise`` object: its network inputs' noise (:func:`~service.preprocess.noise.input_noise`;
    null where no slice holds enough brain to tell), whether it is beyond what the network learnt and
    the pipeline's benchmarks hold (:data:`~service.preprocess.noise.NOISY_INPUT`), and what it added
    to each slice's expected error (``added_mm``, in quadrature; the model's noise calibration).

    Example:
        >>> noise_report(0.1244, 2.13), noise_report(float("nan"))  # doctest: +NORMALIZE_WHITESPACE
        ({'input_noise': 0.1244, 'beyond_calibration': True, 'expected_error_added_mm': 2.13},
         {'input_noise': None, 'beyond_calibration': False, 'expected_error_added_mm': 0.0})
    """
    known = bool(np.isfinite(level))
    return {"input_noise": round(float(level), 4) if known else None,
            "beyond_calibration": bool(known and level > NOISY_INPUT),
            "expected_error_added_mm": round(float(added_mm), 2)}


def frame_report(network_error_mm: float, added_mm: float = 0.0) -> dict:
    """A stack's ``frame`` object: the request's network error (the slice-weighted RMS of its stacks'
    ``network_error_mm`` over those whose fit is decidable; null where none is), which the request's
    placement in the atlas frame is worse with, and what that added to each slice's expected error
    (``added_mm``, in quadrature; the model's ``frame_error`` calibration,
    :mod:`service.consistency.frame_error`). Every stack of a request has the same.

    Example:
        >>> frame_report(23.64, 5.318), frame_report(float("nan"))
        ({'request_network_error_mm': 23.6, 'expected_error_added_mm': 5.32}, {'request_network_error_mm': None, 'expected_error_added_mm': 0.0})
    """
    known = bool(np.isfinite(network_error_mm))
    return {"request_network_error_mm": round(float(network_error_mm), 1) if known else None,
            "expected_error_added_mm": round(float(added_mm), 2)}
