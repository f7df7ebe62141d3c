"""What the pose error of a held-out brain is made of: its acquisition's common frame, and whether
that frame is the brain's own (the same in every acquisition) or noise.

Part 1. For each validation volume, ``--per-volume`` acquisitions per motion level are predicted
through ``/v1/predict``'s pipeline (masks given, every stage on). Per acquisition: the mean E.D.
of its posed slices against the truth (on the nearer twin), the common frame ``F`` of its errors (the
Fréchet mean of ``P_k T_k^-1`` about the brain's centre: rotation vector, degrees, and shift, mm)
and the mean E.D. left once ``F`` is undone (the error a reconstruction's slice registration can
act on). Per volume: the mean and spread of ``F`` over its acquisitions. A mean far larger than the
spread is the brain's own frame offset, which no number of slices or acquisitions averages away.

Part 2. Where a brain's neighbours put it. Each validation brain is registered rigidly (SimpleITK,
correlation on the skull-stripped images, started at the identity: all volumes share the atlas
space) to the two training brains nearest in age of each population. The registration implies
the frame a network trained on those brains would see the held-out brain in: ``M^-1`` about its
centre, ``M`` the registration (neighbour -> held-out brain). Printed beside part 1's mean frame.

Part 3. Where each held-out brain's own mid-sagittal plane lies. The atlas space is symmetric about
``x = 0``; a brain whose midline lies off that plane has its own mirror twin elsewhere. The brain is
registered rigidly onto its mirror image (across ``x = 0``); half that move, ``H`` (about its
centre), brings its midline onto the plane: the brain's own placement in a symmetric atlas space.
Components a mirror cannot see (a turn about x, shifts in y and z) come out zero. Printed beside
part 1's mean frame ``F`` and ``F H^-1``, what is left of ``F`` against that placement.

    .venv/bin/python model_export/experiments/frame_bias.py [--levels mild,jumps] [--per-volume 3]
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.acquisitions import simulate_acquisition  # noqa: E402
from model_export.atlas import DEFAULT_ATLAS_ROOT, VALIDATION_VOLUMES, AtlasVolume, load_volumes  # noqa: E402
from model_export.evaluate_acquisitions import run_acquisition  # noqa: E402
from model_export.localiser.pose_accuracy import pose_estimator  # noqa: E402
from service.pipeline.documents import stack_objects  # noqa: E402
from service.geometry import anchors, se3, twin  # noqa: E402
from service.geometry.pose import about_centre, make_pose, translate  # noqa: E402
from service.io.volume import Volume  # noqa: E402
from service.reconstruction import midline  # noqa: E402


def common_frame(final: NDArray, truth: NDArray, centre: NDArray) -> tuple[NDArray, NDArray]:
    """The acquisition's common error ``F`` (about ``centre``) of poses ``final`` against ``truth``
    ``[n, 4, 4]``, and each slice's E.D. once it is undone."""
    about = translate(centre)
    frame = se3.frechet_mean(se3.inverse(about)[None] @ final @ se3.inverse(truth) @ about[None])
    undone = se3.inverse(about_centre(frame, centre))[None] @ final
    return frame, anchors.ed(undone, truth)


def as_row(frame: NDArray) -> NDArray[np.float64]:
    """``[6]`` rotation vector (degrees) and shift (mm) of a frame about the brain's centre."""
    return np.r_[np.degrees(se3.so3_log(frame[:3, :3])), frame[:3, 3]]


def acquisition_frames(volume: AtlasVolume, estimator, level: str, count: int,  # noqa: ANN001
                       rng: np.random.Generator) -> list[tuple[float, float, NDArray]]:
    """Per acquisition: mean E.D. against the truth (nearer twin), mean E.D. with the common frame
    undone, and the frame (:func:`as_row`)."""
    plane = estimator.info.symmetry_plane_x_mm
    out = []
    for _ in range(count):
        stacks = simulate_acquisition(volume.image, volume.mask, volume.affine, rng, level)
        predictions, prepared, truth = run_acquisition(stacks, estimator)
        finals, trues = [], []
        for res, p, true in zip(stack_objects(predictions[0]), prepared, truth):
            final = np.array([s["atlas_from_voxel"] for s in res["slices"]]) @ np.linalg.inv(p.network_from_voxel())
            posed = np.array([s["reason"] != "empty" for s in res["slices"]])
            finals.append(final[posed])
            trues.append(twin.nearer(final, true, plane)[posed])
        final, true = np.concatenate(finals), np.concatenate(trues)
        frame, left = common_frame(final, true, volume.centre)
        out.append((float(anchors.ed(final, true).mean()), float(left.mean()), as_row(frame)))
    return out


def register_rigid(fixed: AtlasVolume, moving: AtlasVolume) -> NDArray[np.float64]:
    """``4 x 4`` atlas RAS: rigid registration of ``moving``'s brain to ``fixed``'s (a point of ``fixed`` ->
    the same anatomy in ``moving``; :func:`service.reconstruction.midline.register_rigid`)."""
    return midline.register_rigid(Volume(fixed.image, fixed.affine), Volume(moving.image, moving.affine),
                                  fixed.mask, moving.mask, moving.centre)


def midline_offset(volume: AtlasVolume) -> NDArray[np.float64]:
    """``4 x 4`` (about the brain's centre, atlas RAS) that brings the brain's own mid-sagittal plane
    onto the atlas's: half its rigid registration onto its mirror image (Part 3;
    :func:`service.reconstruction.midline.midline_offset`)."""
    return midline.midline_offset(Volume(volume.image, volume.affine), volume.mask, twin.DEFAULT_PLANE_X_MM)[0]


def age(name: str) -> int:
    return int(re.findall(r"\d+", name)[0])


def fmt(row: NDArray) -> str:
    return f"rot ({', '.join(f'{x:+.1f}' for x in row[:3])})°  shift ({', '.join(f'{x:+.1f}' for x in row[3:])}) mm"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--levels", default="mild,jumps")
    ap.add_argument("--per-volume", type=int, default=3)
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args()
    every = load_volumes(None, DEFAULT_ATLAS_ROOT)
    held_out = [v for v in every if v.name in VALIDATION_VOLUMES]
    estimator, rng = pose_estimator(), np.random.default_rng(args.seed)
    means: dict[str, list[NDArray]] = {}
    for level in args.levels.split(","):
        print(f"\n## {level}\n\n| volume | mean E.D. | frame undone | frame's mean over acquisitions | its spread (sd) |\n|---|---|---|---|---|")
        for v in held_out:
            rows = acquisition_frames(v, estimator, level, args.per_volume, rng)
            frames = np.array([r[2] for r in rows])
            means.setdefault(v.name, []).append(frames.mean(axis=0))
            print(f"| {v.name} | {np.mean([r[0] for r in rows]):.2f} | {np.mean([r[1] for r in rows]):.2f} "
                  f"| {fmt(frames.mean(axis=0))} | {fmt(frames.std(axis=0, ddof=1))} |", flush=True)
    print("\n## Where the nearest training brains put each held-out brain\n\n| volume | frame (mean of part 1) | "
          "by | implied frame |\n|---|---|---|---|")
    for v in held_out:
        others = sorted((o for o in every if o.name not in VALIDATION_VOLUMES), key=lambda o: abs(age(o.name) - age(v.name)))
        for population in ("crl_sta", "spina_bifida_cc0"):
            for o in [o for o in others if o.population == population][:2]:
                about = translate(v.centre)
                implied = se3.inverse(about) @ np.linalg.inv(register_rigid(o, v)) @ about
                print(f"| {v.name} | {fmt(np.mean(means[v.name], axis=0))} | {o.name} | {fmt(as_row(implied))} |", flush=True)
    print("\n## Each held-out brain's midline against the atlas plane\n\n| volume | frame F (mean of part 1) | "
          "midline offset H | F H^-1 | its size |\n|---|---|---|---|---|")
    for v in held_out:
        frame = np.mean(means[v.name], axis=0)
        f = make_pose(se3.so3_exp(np.radians(frame[:3])), frame[3:])
        h = midline_offset(v)
        left = as_row(f @ se3.inverse(h))
        print(f"| {v.name} | {fmt(frame)} | {fmt(as_row(h))} | {fmt(left)} | {np.linalg.norm(left[:3]):.1f}°, "
              f"{np.linalg.norm(left[3:]):.1f} mm |", flush=True)


if __name__ == "__main__":
    main()
