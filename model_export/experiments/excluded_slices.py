"""Where a job's error lies at a motion level: the slices in its volume against those left out, and
what registering the left-out ones to the volume does to them.

A job starts from `/v1/predict`'s poses and puts only the accepted slices in its volume
(:func:`service.jobs.starting_poses.starting_poses`); the others keep their predicted poses. For each
simulated acquisition of the validation volumes: the slice level (``coarse_to_fine`` off, 3 rounds)
is run; the mean and median E.D. against the truth in the acquisition's own frame (its common
frame undone) are printed for the slices in the volume and those left out, before and after; then
the left-out slices are registered to the job's volume (rounds of ``--schedule``: trust radius mm,
extra blur mm) and their E.D. printed again, with how many got more than 2 mm worse, and whether
their NCC with the volume rose. Needs ``../shared/data``.

    .venv/bin/python model_export/experiments/excluded_slices.py [--level independent] [--acquisitions 2]
        [--schedule 4:2,2:1,1:0,1:0] [--seed 11]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.acquisitions import simulate_acquisition  # noqa: E402
from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes, split  # noqa: E402
from model_export.evaluate_acquisitions import MIN_MASK_PIXELS, run_acquisition  # noqa: E402
from model_export.experiments.refine_bench import network_poses, to_truth_frame  # noqa: E402
from service.pipeline.documents import stack_objects  # noqa: E402
from service.geometry.anchors import ed  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator  # noqa: E402
from service.inference.model_file import load_model  # noqa: E402
from service.jobs.starting_poses import MIN_ACCEPTED_SHARE, starting_poses  # noqa: E402
from service.reconstruction.forward import inplane_sigma_mm  # noqa: E402
from service.reconstruction.config import ReconstructionConfig  # noqa: E402
from service.reconstruction.pipeline import reconstruct  # noqa: E402
from service.reconstruction.registration import register_slices  # noqa: E402
from service.reconstruction.slices import SliceSet  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--level", default="independent")
    ap.add_argument("--acquisitions", type=int, default=2)
    ap.add_argument("--schedule", default="4:2,2:1,1:0,1:0", help="registration rounds, trust radius:extra blur (mm)")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--model", default="service/models/default/model.onnx")
    args = ap.parse_args()
    schedule = [tuple(float(v) for v in r.split(":")) for r in args.schedule.split(",")]
    est = OnnxPoseEstimator(load_model(Path(args.model)))
    vols = load_volumes(split(DEFAULT_ATLAS_ROOT)[1], DEFAULT_ATLAS_ROOT)
    rng = np.random.default_rng(args.seed)
    for a in range(args.acquisitions):
        vol = vols[a % len(vols)]
        stacks = simulate_acquisition(vol.image, vol.mask, vol.affine, rng, args.level)
        (predictions,), prepared, _ = run_acquisition(stacks, est, 100, True)
        masks = [p.slices.to_stack(p.slices.masks) for p in prepared]
        poses = starting_poses({"stacks": stack_objects(predictions)}, MIN_ACCEPTED_SHARE)
        job_set = SliceSet.from_stacks([(s.volume, m, mats, inc) for s, m, (mats, inc) in zip(stacks, masks, poses)])
        every = SliceSet.from_stacks([(s.volume, m, mats, np.ones(len(mats), bool))
                                      for s, m, (mats, _) in zip(stacks, masks, poses)])
        keep = np.concatenate([p.prepared.mask_pixels >= MIN_MASK_PIXELS for p in prepared])

        def own_frame(transforms: np.ndarray) -> np.ndarray:
            pose, true = network_poses(stacks, prepared, transforms)
            pose, true = pose[keep], true[keep]
            return ed(to_truth_frame(pose, true) @ pose, true)

        config = ReconstructionConfig(symmetry_plane_x_mm=est.info.symmetry_plane_x_mm, coarse_to_fine=False)
        res = reconstruct(job_set, resolution_mm=1.5, svr_iterations=3, config=config)
        inside = job_set.include[keep]
        before, after = own_frame(job_set.atlas_from_voxel), own_frame(res.atlas_from_voxel_final)
        left_out = ~job_set.include & every.include
        moved, base = res.atlas_from_voxel_final.copy(), inplane_sigma_mm(every)
        start = register_slices(res.volume.array, res.grid, every, moved, active=left_out, max_iterations=0)
        for step, extra in schedule:
            reg = register_slices(res.volume.array, res.grid, every, moved, active=left_out, max_iterations=30,
                                  step_mm=step, blur_sigma_mm=float(np.hypot(base, extra)))
            moved = reg.atlas_from_voxel
        registered = own_frame(moved)
        out = ~inside
        rose = np.nanmean(reg.ncc[left_out] > start.ncc[left_out])
        print(f"{args.level} {vol.name}: {int(inside.sum())}/{len(inside)} slices in the volume; own-frame E.D. mean "
              f"(median), mm: in the volume {before[inside].mean():.2f} -> {after[inside].mean():.2f}, left out "
              f"{before[out].mean():.2f} ({np.median(before[out]):.2f}) -> {after[out].mean():.2f}; left out and "
              f"registered {registered[out].mean():.2f} ({np.median(registered[out]):.2f}), "
              f"{int(((registered - after)[out] > 2).sum())} of {int(out.sum())} more than 2 mm worse, NCC rose "
              f"for {rose:.0%}", flush=True)


if __name__ == "__main__":
    main()
