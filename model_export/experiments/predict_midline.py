"""A midline step for ``/v1/predict``: does putting each answer's own midline on the atlas plane
bring a real scan's no-mask and manual-mask answers together?

A job's midline step (:func:`~service.reconstruction.midline.midline_fit`) corrects the three
degrees of freedom a brain's symmetry shows (turns about y and z, a shift along x) on its
reconstruction. Here each ``/v1/predict`` answer (manual masks sent with ``masks_hold_csf``, and
none) gets the same step on a quick volume: the Gaussian average of its accepted slices at
``--resolution`` mm (:func:`~service.reconstruction.gaussian_average.gaussian_average`). Printed per
seed of the model's fixed draws: each answer's correction (rotation vector, degrees) and its time,
then the two answers' median E.D. over the slices both accept and their common rigid offset, as
``/v1/predict`` gives them and with each corrected.

    .venv/bin/python model_export/experiments/predict_midline.py [SCAN_FOLDER] [--resolution 2.0] [--seeds 0,1]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.experiments.frame_bias import common_frame  # noqa: E402
from model_export.experiments.real_scan_poses import read_scan  # noqa: E402
from model_export.localiser.evaluate import REAL_SCANS  # noqa: E402
from model_export.localiser.pose_accuracy import pose_estimator  # noqa: E402
from service.geometry import anchors, se3  # noqa: E402
from service.inference.acceptance import ATLAS_CENTRE_MM  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator  # noqa: E402
from service.io.volume import Volume  # noqa: E402
from service.jobs.starting_poses import starting_poses  # noqa: E402
from service.jobs.worker import predicted_body  # noqa: E402
from service.pipeline.prepare import StackUpload, prepare_stacks  # noqa: E402
from service.preprocess.localise import default_localiser  # noqa: E402
from service.reconstruction.gaussian_average import gaussian_average  # noqa: E402
from service.reconstruction.grid import bounds_of, make_grid  # noqa: E402
from service.reconstruction.midline import FrameCorrection, midline_fit  # noqa: E402
from service.reconstruction.slices import SliceSet  # noqa: E402


def quick_midline(body: dict, uploads: list[StackUpload], masks: list[NDArray], plane_x_mm: float,
                  resolution_mm: float) -> FrameCorrection:
    """The midline correction of an answer's accepted slices, averaged at ``resolution_mm``."""
    inputs = [(u.volume, m, mats, accepted) for u, m, (mats, accepted) in zip(uploads, masks, starting_poses(body))]
    slices = SliceSet.from_stacks(inputs)
    poses = np.concatenate([mats for _, _, mats, _ in inputs])
    grid = make_grid(resolution_mm, bounds_of(slices.positions(poses), 10.0))
    return midline_fit(Volume(gaussian_average(slices, poses, grid).volume, grid.affine.copy()), plane_x_mm)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scan", type=Path, nargs="?", default=REAL_SCANS / "mial_lausanne_t30")
    ap.add_argument("--resolution", type=float, default=2.0)
    ap.add_argument("--seeds", default="0,1")
    args = ap.parse_args()
    base, localiser = pose_estimator(None), default_localiser()
    plane = base.info.symmetry_plane_x_mm
    volumes, manual = read_scan(args.scan)
    names = list(volumes)
    for seed in (int(s) for s in args.seeds.split(",")):
        estimator = base if seed == 0 else OnnxPoseEstimator(base.model.with_seed(base.model.mc_seed + seed))
        answers = []
        for with_masks in (True, False):
            uploads = [StackUpload(n, volumes[n], manual[n] if with_masks else None,
                                   f"{n}_brain_mask" if with_masks else None, mask_holds_csf=with_masks) for n in names]
            if with_masks:             # one slice frame for both answers: the manual masks' preparation
                prepared = prepare_stacks(uploads, estimator.info, True, workers=2, localiser=localiser)
                voxel_from_slice = np.concatenate([np.linalg.inv(p.slices.slice_from_voxel) for p in prepared])
            body, masks = predicted_body(uploads, estimator, 100, localiser=localiser)
            start = time.perf_counter()
            fit = quick_midline(body, uploads, masks, plane, args.resolution)
            seconds = time.perf_counter() - start
            poses = np.array([s["atlas_from_voxel"] for st in body["stacks"] for s in st["slices"]])
            accepted = np.array([s["accepted"] for st in body["stacks"] for s in st["slices"]])
            print(f"seed {seed}, {'manual masks' if with_masks else 'no masks'}: correction "
                  f"{np.round(np.degrees(se3.so3_log(fit.correction[:3, :3])), 1).tolist()} deg, "
                  f"{np.round(fit.correction[:3, 3], 1).tolist()} mm (applied: {fit.applied}), {seconds:.2f} s", flush=True)
            answers.append((poses, accepted, fit.correction))
        (pa, ka, ca), (pb, kb, cb) = answers
        both = ka & kb
        for label, a, b in (("as /v1/predict", pa, pb), ("each with its midline step", ca @ pa, cb @ pb)):
            a, b = a[both] @ voxel_from_slice[both], b[both] @ voxel_from_slice[both]
            frame, _ = common_frame(b, a, ATLAS_CENTRE_MM)
            print(f"  {label}: {both.sum()} slices, median E.D. {np.median(anchors.ed(a, b)):.2f} mm; common "
                  f"{np.linalg.norm(frame[:3, 3]):.2f} mm / {np.degrees(np.linalg.norm(se3.so3_log(frame[:3, :3]))):.2f} deg",
                  flush=True)


if __name__ == "__main__":
    main()
