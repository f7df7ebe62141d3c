"""A real scan's job without masks against the job with its manual masks: do the job's frame steps
bring the two answers together where ``/v1/predict``'s stay apart?

Real scans have no true poses, but two answers for the same stacks can be compared
(``real_scan_poses.py`` does it for ``/v1/predict``). Here each answer also goes through what a job
runs (the never-worse paths at 1.5 mm, the left-out slices placed, the atlas frame, the midline;
:mod:`service.jobs.worker`), and the two are compared at each step over the slices both place (both
accept, for the predictions): the median E.D., the common rigid offset about the brain's centre
(:func:`~model_export.experiments.frame_bias.common_frame`) and the median E.D. once it is undone.
Every pose is taken in the slice frames of the manual masks' preparation, so both answers are
measured in one frame. A folder holds ``NAME.nii.gz`` beside ``NAME_brain_mask.nii.gz``. Run:
``.venv/bin/python model_export/experiments/job_mask_agreement.py [SCAN_FOLDER]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.experiments.frame_bias import common_frame  # noqa: E402
from model_export.experiments.real_scan_poses import read_scan  # noqa: E402
from model_export.localiser.evaluate import REAL_SCANS  # noqa: E402
from model_export.localiser.pose_accuracy import pose_estimator  # noqa: E402
from service.geometry import anchors, se3  # noqa: E402
from service.inference.acceptance import ATLAS_CENTRE_MM  # noqa: E402
from service.jobs.uploaded_poses import expected_errors  # noqa: E402
from service.jobs.starting_poses import starting_poses  # noqa: E402
from service.jobs.worker import predicted_body  # noqa: E402
from service.pipeline.prepare import StackUpload, prepare_stacks  # noqa: E402
from service.preprocess.localise import default_localiser  # noqa: E402
from service.reconstruction.job import refine_job  # noqa: E402
from service.reconstruction.pose_errors import LEFT_OUT  # noqa: E402
from service.reconstruction.slices import SliceSet  # noqa: E402

STEPS = ("predicted", "job before the frame steps", "job after the atlas frame", "job as returned (midline)")


def answer(uploads: list[StackUpload], estimator, localiser, plane: float) -> dict:  # noqa: ANN001
    """``atlas_from_voxel`` of every slice after each of :data:`STEPS`, and which slices count at each
    (accepted for the prediction, placed for the job's)."""
    body, masks = predicted_body(uploads, estimator, 100, localiser=localiser)
    inputs = [(u.volume, m, mats, acc) for u, m, (mats, acc) in zip(uploads, masks, starting_poses(body))]
    job = refine_job(SliceSet.from_stacks(inputs), inputs, expected_errors(body), estimator=estimator,
                     plane_x_mm=plane, resolution_mm=1.5, svr_iterations=3)
    before = job.left_out.poses                                     # the poses before the frame steps
    framed = (job.frame.correction if job.frame.applied else np.eye(4)) @ before
    slices = [s for st in body["stacks"] for s in st["slices"]]
    placed = job.role != LEFT_OUT
    return {"poses": [np.array([s["atlas_from_voxel"] for s in slices]), before, framed,
                      job.result.atlas_from_voxel_final],
            "use": [np.array([bool(s["accepted"]) for s in slices]), placed, placed, placed]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scan", type=Path, nargs="?", default=REAL_SCANS / "mial_lausanne_t30")
    args = ap.parse_args()
    estimator, localiser = pose_estimator(None), default_localiser()
    plane = estimator.info.symmetry_plane_x_mm
    volumes, manual = read_scan(args.scan)
    names = list(volumes)
    answers = []
    for with_masks in (True, False):
        uploads = [StackUpload(n, volumes[n], manual[n] if with_masks else None, f"{n}_brain_mask" if with_masks else None,
                               mask_holds_csf=with_masks) for n in names]
        if with_masks:                 # one slice frame for both answers: the manual masks' preparation
            prepared = prepare_stacks(uploads, estimator.info, True, workers=2, localiser=localiser)
            voxel_from_slice = np.concatenate([np.linalg.inv(p.slices.slice_from_voxel) for p in prepared])
        answers.append(answer(uploads, estimator, localiser, plane))
        print(f"{'with' if with_masks else 'without'} masks: {answers[-1]['use'][0].sum()} slices accepted, "
              f"{answers[-1]['use'][1].sum()} placed by the job", flush=True)
    manual_answer, no_mask = answers
    for k, step in enumerate(STEPS):
        use = manual_answer["use"][k] & no_mask["use"][k]
        a, b = manual_answer["poses"][k][use] @ voxel_from_slice[use], no_mask["poses"][k][use] @ voxel_from_slice[use]
        frame, left = common_frame(b, a, ATLAS_CENTRE_MM)
        turn = np.degrees(np.linalg.norm(se3.so3_log(frame[:3, :3])))
        print(f"{step}: {use.sum()} slices, median E.D. {np.median(anchors.ed(a, b)):.2f} mm; common offset "
              f"{np.linalg.norm(frame[:3, 3]):.2f} mm / {turn:.2f} deg; once undone {np.median(left):.2f} mm")


if __name__ == "__main__":
    main()
