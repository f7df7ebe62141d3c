"""What placing the left-out slices by their stack's motion does to a job's poses
(:mod:`service.reconstruction.left_out`), on simulated 3-stack acquisitions of the validation volumes.

Each acquisition is predicted through the server's pipeline and reconstructed as a job does (the
never-worse paths, 1.5 mm, 3 rounds); the left-out slices are then placed. Printed per acquisition
and level: how many left-out slices moved, their mean E.D. in the acquisition's own frame (its
common frame undone) before and after, and every slice's mean E.D. against the truth and twin-min,
without the step, with the motion model's moves alone, with those beside jumps too, and with the
left-out slices then registered to the volume (before the frame steps), and on how many acquisitions
the whole step made the twin-min mean worse. Needs ``../shared/data``.

    .venv/bin/python model_export/experiments/left_out_slices.py [--levels mild,moderate,jumps,independent]
        [--per-level 5] [--seed 5]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.acquisitions import simulate_acquisition  # noqa: E402
from model_export.evaluate_acquisitions import MIN_MASK_PIXELS, run_acquisition  # noqa: E402
from model_export.experiments.refine_bench import network_poses, to_truth_frame, validation_setup  # noqa: E402
from service.pipeline.documents import stack_objects  # noqa: E402
from service.geometry import twin  # noqa: E402
from service.geometry.anchors import ed  # noqa: E402
from service.jobs.uploaded_poses import expected_errors  # noqa: E402
from service.jobs.starting_poses import MIN_ACCEPTED_SHARE, starting_poses  # noqa: E402
from service.reconstruction.left_out import VolumeReference, place_left_out  # noqa: E402
from service.reconstruction.never_worse import reconstruct_never_worse  # noqa: E402
from service.reconstruction.config import ReconstructionConfig  # noqa: E402
from service.reconstruction.slices import SliceSet  # noqa: E402


def mean(values: np.ndarray) -> float:
    """The mean, NaN for none (an acquisition whose left-out slices all lack brain pixels)."""
    return float(values.mean()) if len(values) else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--levels", default="mild,moderate,jumps,independent")
    ap.add_argument("--per-level", type=int, default=5)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--model", default="service/models/default/model.onnx")
    args = ap.parse_args()
    est, plane, vols = validation_setup(args.model)
    rng = np.random.default_rng(args.seed)
    for level in args.levels.split(","):
        rows: dict[str, list] = {"job": [], "by the motion model": [], "and beside jumps": [], "and by the volume": []}
        worse = 0
        for a in range(args.per_level):
            vol = vols[a % len(vols)]
            stacks = simulate_acquisition(vol.image, vol.mask, vol.affine, rng, level)
            (predictions,), prepared, _ = run_acquisition(stacks, est, 100, True)
            body = {"stacks": stack_objects(predictions)}
            masks = [p.slices.to_stack(p.slices.masks) for p in prepared]
            inputs = [(s.volume, m, mats, inc) for s, m, (mats, inc)
                      in zip(stacks, masks, starting_poses(body, MIN_ACCEPTED_SHARE))]
            ss = SliceSet.from_stacks(inputs)
            res = reconstruct_never_worse(ss, 1.5, 3, config=ReconstructionConfig(symmetry_plane_x_mm=plane))
            placed = place_left_out(ss, res.atlas_from_voxel_final, res.included, expected_errors(body), plane_x_mm=plane)
            by_volume = place_left_out(ss, res.atlas_from_voxel_final, res.included, expected_errors(body),
                                       plane_x_mm=plane, volume=VolumeReference.of(res, inputs))
            keep = np.concatenate([p.prepared.mask_pixels >= MIN_MASK_PIXELS for p in prepared])

            def scores(transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
                pose, true = network_poses(stacks, prepared, transforms)
                pose, true = pose[keep], true[keep]
                return ed(to_truth_frame(pose, true) @ pose, true), ed(pose, true), twin.twin_min_ed(pose, true, plane)

            by_model = placed.poses.copy()
            by_model[placed.beside_jump] = res.atlas_from_voxel_final[placed.beside_jump]
            before, after, registered = (scores(res.atlas_from_voxel_final), scores(placed.poses),
                                         scores(by_volume.poses))
            rows["job"].append(before)
            rows["by the motion model"].append(scores(by_model))
            rows["and beside jumps"].append(after)
            rows["and by the volume"].append(registered)
            out, moved = ~res.included[keep], placed.moved[keep]
            worse += int(registered[2].mean() > before[2].mean() + 1e-9)
            print(f"{level} {vol.name}: {int(moved.sum())} of {int(out.sum())} left-out slices moved "
                  f"({int(placed.beside_jump[keep].sum())} beside a jump, twin-min without them "
                  f"{rows['by the motion model'][-1][2].mean():.2f} mm); left out, own "
                  f"frame {mean(before[0][out]):.2f} -> {mean(after[0][out]):.2f} mm; all slices, truth / twin-min "
                  f"{before[1].mean():.2f} / {before[2].mean():.2f} -> {after[1].mean():.2f} / {after[2].mean():.2f} mm; "
                  f"{int(by_volume.registered[keep].sum())} registered to the volume: left out, own frame "
                  f"{mean(registered[0][out]):.2f} mm, all slices {registered[1].mean():.2f} / "
                  f"{registered[2].mean():.2f} mm", flush=True)
        for name, v in rows.items():
            own, truth, tmin = (np.concatenate([x[i] for x in v]).mean() for i in range(3))
            print(f"== {level} {name}: mean E.D. own frame {own:.2f}, truth {truth:.2f}, twin-min {tmin:.2f} mm", flush=True)
        print(f"== {level}: acquisitions worse with the step (twin-min) {worse} of {args.per_level}", flush=True)


if __name__ == "__main__":
    main()
