"""Refined poses of a reconstruction job against the truth, on simulated 3-stack acquisitions, and
what each stage of the job does to them (ablations).

For each motion level (``--levels``; the smooth ones and those with jumps), acquisitions of the
validation volumes (``model_export.acquisitions``) are predicted by the shipped model through the
server's pipeline (stack consistency, the stacks pooled), then reconstructed as a job does from the
service's own poses (the accepted slices, or every slice: ``--start-shares``; coarse-to-fine, SVR rounds), once per ``--variants``
(:data:`VARIANTS`: the full reconstruction, it without one of its stages, and ``job``: what a job
runs, the never-worse choice of :mod:`service.reconstruction.never_worse`, then the left-out slices
placed by their stacks' motion, :mod:`service.reconstruction.left_out`). Printed per level and
variant: the mean E.D. (mm, slices with >= 20 mask pixels, network frames; against the truth,
twin-min, and the truth in the acquisition's own frame) of the predicted and of the refined poses,
on how many acquisitions the refined poses are worse than the predicted ones, the quality report's
leave-one-stack-out NCC (what a user sees without the truth), the volume's PSNR and NCC against the truth (as
placed, frame-free, and with ``--midline`` midline-placed) and the seconds of each reconstruction. ``--atlas-frame`` adds each variant with its atlas frame re-estimated by the
network (``service/reconstruction/atlas_frame.py``), and then with its midline put on the atlas plane
(``service/reconstruction/midline.py``), as a job does; ``--midline`` adds twin-min against the truth moved so
that the brain's own midline lies on the atlas plane (a brain off that plane has no mirror twin in a
symmetric atlas space: ``frame_bias.py``, part 3). Every variant reconstructs the stacks as a job's
worker does, bias-corrected by N4 (:func:`~service.reconstruction.job.bias_corrected_stacks`; figures
before 2026-12-05 were made on the stacks as acquired), but the ``job-raw-stacks`` ones.
``--shading`` and ``--slice-gain`` change the stacks' intensities as a coil and a single-shot
sequence do (:func:`~model_export.experiments.scanner_sweep.with_shading`). Needs ``../shared/data``
(the atlas volumes). Run:
``.venv/bin/python model_export/experiments/refine_bench.py [--levels mild,jumps] [--variants default,no-coarse]
[--per-level 6] [--resolution 1.5] [--rounds 3]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes, split
from model_export.calibrate_noise import acquire
from model_export.evaluate_acquisitions import MIN_MASK_PIXELS, run_acquisition
from model_export.experiments.frame_bias import midline_offset
from model_export.experiments.scanner_sweep import with_shading, with_signal_loss
from model_export.volume_metrics import volume_psnr_ncc
from service.pipeline.documents import stack_objects
from service.geometry import se3, twin
from service.geometry.anchors import ed
from service.geometry.pose import about_centre
from service.inference.estimator import OnnxPoseEstimator
from service.inference.model_file import load_model
from service.jobs.uploaded_poses import expected_errors
from service.jobs.starting_poses import MIN_ACCEPTED_SHARE, starting_poses
from service.reconstruction.atlas_frame import atlas_frame, with_frame
from service.reconstruction.job import bias_corrected_stacks
from service.reconstruction.left_out import LeftOutPlacement, VolumeReference, place_left_out
from service.reconstruction.midline import midline_fit
from service.reconstruction.held_out import held_out_score
from service.reconstruction.never_worse import reconstruct_never_worse
from service.reconstruction.config import ReconstructionConfig
from service.reconstruction.pipeline import reconstruct
from service.reconstruction.slices import SliceSet


def errors(stacks, prepared, poses, plane_x_mm: float, midline: np.ndarray | None = None) -> np.ndarray:
    """``[3, N]`` E.D. of ``poses`` (``atlas_from_voxel``, all stacks) against the truth, twin-min
    (the nearer of the truth and its left-right twin), and against the truth once the
    acquisition's common frame error is taken out (one rigid atlas -> atlas map for all its slices:
    what the reconstruction keeps as its frame), in network frames. With ``midline`` (the atlas ->
    atlas map that brings the brain's own midline onto the atlas plane,
    :func:`~model_export.experiments.frame_bias.midline_offset` about its centre), ``[4, N]``: also
    twin-min against the truth so placed."""
    keep = np.concatenate([p.prepared.mask_pixels >= MIN_MASK_PIXELS for p in prepared])
    pose, true = network_poses(stacks, prepared, poses)
    pose, true = pose[keep], true[keep]
    frame = to_truth_frame(pose, true)
    rows = [ed(pose, true), twin.twin_min_ed(pose, true, plane_x_mm), ed(frame @ pose, true)]
    if midline is not None:
        rows.append(twin.twin_min_ed(pose, midline @ true, plane_x_mm))
    return np.stack(rows)


def left_out_changes(stacks, prepared, starting: np.ndarray, included: np.ndarray, left_out: LeftOutPlacement,  # noqa: ANN001
                     plane_x_mm: float) -> str:
    """Mean twin-min E.D. (mm) from the starting poses to the job's, per group of slices: those in the
    volume, and the left-out ones by what :func:`~service.reconstruction.left_out.place_left_out` did."""
    keep = np.concatenate([p.prepared.mask_pixels >= MIN_MASK_PIXELS for p in prepared])
    before, after = (errors(stacks, prepared, poses, plane_x_mm)[1] for poses in (starting, left_out.poses))
    out = ~included & ~left_out.moved & ~left_out.registered
    groups = {"in the volume": included, "left out, moved by motion": left_out.moved & ~left_out.beside_jump,
              "beside a jump": left_out.beside_jump, "registered": left_out.registered, "left where they were": out}
    return "; ".join(f"{name} {int(g[keep].sum())}: {before[g[keep]].mean():.2f} -> {after[g[keep]].mean():.2f}"
                     for name, g in groups.items() if g[keep].any())


def network_poses(stacks, prepared, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001
    """``(pose, true)`` ``[N, 4, 4]``: ``poses`` (``atlas_from_voxel``, all stacks) and the simulated truth,
    both in the network frames of the ``prepared`` stacks."""
    voxel_from_network = np.concatenate([np.linalg.inv(p.network_from_voxel()) for p in prepared])
    return poses @ voxel_from_network, np.concatenate([s.atlas_from_voxel for s in stacks]) @ voxel_from_network


def to_truth_frame(pose: np.ndarray, true: np.ndarray) -> np.ndarray:
    """The acquisition's common frame error, as the atlas -> atlas map from where ``pose`` puts the
    slices to where ``true`` does (Fréchet mean of ``true pose^-1``; ``frame_bias.common_frame`` is
    its inverse, about the brain's centre)."""
    return se3.frechet_mean(true @ se3.inverse(pose), np.ones(len(pose)))


def psnrs(res, vol, stacks, prepared, mid: np.ndarray | None) -> list[float]:  # noqa: ANN001
    """The volume's PSNR (dB) against the truth as placed, frame-free (the frame its poses share
    undone) and, with ``mid``, against the truth placed with its midline on the atlas plane; then its
    NCC the same ways."""
    pose, true = network_poses(stacks, prepared, res.atlas_from_voxel_final)
    used = res.included
    frames = [None, se3.inverse(to_truth_frame(pose[used], true[used]))] + ([mid] if mid is not None else [])
    scores = [volume_psnr_ncc(res.volume, vol.image, vol.mask, vol.affine, frame=f) for f in frames]
    return [s[0] for s in scores] + [s[1] for s in scores]


VARIANTS: dict[str, dict] = {
    "default": {},
    "no-coarse": {"coarse_to_fine": False},              # no stack fit, stack registration, own-or-stack start
    "no-folds": {"leave_out_folds": 1},                  # register to the whole volume
    "no-capture": {"capture_schedule": ()},              # no wide, blurred first rounds
    "no-robust": {"robust": False},                      # every slice and pixel weighs 1
    "no-anchor": {"anchor_frame": False},                # the slices' common drift kept
    "file-grids": {"stack_follow_motion_mm": float("inf")},
    "no-register": {"register": False},                  # super-resolution at the starting poses
    "no-intensity": {"intensity_matching": False},       # one scale per stack, no slice's gain or shading
    "slice-level": {"coarse_to_fine": False},            # steps 4-5 alone, and each without one of its parts
    "slice-level-no-folds": {"coarse_to_fine": False, "leave_out_folds": 1},
    "slice-level-no-anchor": {"coarse_to_fine": False, "anchor_frame": False},
    "slice-level-no-robust": {"coarse_to_fine": False, "robust": False},
    "slice-level-fine": {"coarse_to_fine": False, "registration_subsample": 1, "registration_psf_points": 5},
    "slice-level-prior1": {"coarse_to_fine": False, "registration_prior_sd_mm": 1.0},
    "slice-level-prior2": {"coarse_to_fine": False, "registration_prior_sd_mm": 2.0},
    "job": {},                                           # what a job runs: the never-worse paths
    "job-one-resolution": {},                            # the same, its paths at the output resolution
    "job-path-left-out": {},                             # the job, its left-out slices from the path's poses
    "job-with-signal-lost": {},                          # the job, started with the slices that lost their signal
    "job-no-intensity": {"intensity_matching": False},   # the job without the slices' gains and shading
    "job-raw-stacks": {},                                # the job on the stacks as acquired (no N4)
    "job-raw-stacks-no-intensity": {"intensity_matching": False},   # neither: a job before 2026-12-05
}
"""Each variant's :class:`ReconstructionConfig` fields (beside the model's symmetry plane)."""
JOBS: dict[str, dict] = {"job": {}, "job-one-resolution": {"path_resolution_mm": None}, "job-path-left-out": {},
                         "job-with-signal-lost": {}, "job-no-intensity": {},
                         "job-raw-stacks": {}, "job-raw-stacks-no-intensity": {}}
"""The variants that run a job's paths (:func:`reconstruct_never_worse`), and its keywords."""


def validation_setup(model: str) -> tuple[OnnxPoseEstimator, float, list]:
    """The pose model of file ``model``, its atlas mid-sagittal plane and the validation volumes;
    exits with a message where the atlas data are absent."""
    if not DEFAULT_ATLAS_ROOT.exists():
        sys.exit(f"needs the atlas volumes at {DEFAULT_ATLAS_ROOT}")
    est = OnnxPoseEstimator(load_model(Path(model)))
    return est, est.info.symmetry_plane_x_mm, load_volumes(split(DEFAULT_ATLAS_ROOT)[1], DEFAULT_ATLAS_ROOT)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="service/models/default/model.onnx")
    ap.add_argument("--per-level", type=int, default=6)
    ap.add_argument("--resolution", type=float, default=1.5)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--atlas-frame", action=argparse.BooleanOptionalAction, default=False,
                    help="also each variant with the reconstruction's atlas frame re-estimated by the network")
    ap.add_argument("--levels", default="mild,moderate,jumps,independent")
    ap.add_argument("--start", choices=("predicted", "truth"), default="predicted",
                    help="the poses the reconstruction starts from (truth: does registration keep them?)")
    ap.add_argument("--pixel-mm", type=float, default=1.0, help="the simulated stacks' pixel size (a 128 mm field of view)")
    ap.add_argument("--noise", type=float, default=0.03, help="their Rician noise, a share of the bright end")
    ap.add_argument("--bias", type=float, default=None, help="the simulated stacks' bias-field strength "
                    "(default: model_export.acquisitions'; 0: none)")
    ap.add_argument("--start-shares", default=str(MIN_ACCEPTED_SHARE),
                    help="comma-separated: each reconstructs from the same prediction, starting from the accepted "
                         "slices when this share of the posed ones is accepted (above 1: from every slice)")
    ap.add_argument("--variants", default="default", help=f"comma-separated, of {', '.join(VARIANTS)}")
    ap.add_argument("--signal-loss", action="store_true", help="a signal loss over the brain in a run of slices of "
                    "every stack (scanner_sweep.with_signal_loss)")
    ap.add_argument("--shading", type=float, default=0.0, help="a linear field of +-this share across each "
                    "stack's brain, another direction per stack (scanner_sweep.with_shading)")
    ap.add_argument("--slice-gain", type=float, default=0.0, help="each slice's own gain, exp(N(0, this))")
    ap.add_argument("--midline", action="store_true", help="also twin-min against the truth moved so that the "
                    "brain's own midline lies on the atlas plane (frame_bias.py's part 3)")
    args = ap.parse_args()
    est, plane, vols = validation_setup(args.model)
    rng = np.random.default_rng(args.seed)
    shares = [float(x) for x in args.start_shares.split(",")]
    variants = [f"{v}@{sh:g}" if len(shares) > 1 else v for v in args.variants.split(",") for sh in shares]
    midlines: dict[str, np.ndarray] = {}
    for level in args.levels.split(","):
        framed = [f"{k}, atlas frame{m}" for k in variants for m in ("", " and midline")] if args.atlas_frame else []
        rows = {"predicted": [], **{k: [] for k in variants}, **{k: [] for k in framed}}
        seconds = {k: [] for k in variants}
        held = {k: [] for k in variants}
        psnr = {k: [] for k in [*variants, *framed]}
        for a in range(args.per_level):
            vol = vols[a % len(vols)]
            stacks = acquire(vol, rng, level, pixel_mm=args.pixel_mm, noise=args.noise,
                             **({} if args.bias is None else {"bias": args.bias}))
            stacks = with_signal_loss(stacks, rng) if args.signal_loss else stacks
            if args.shading or args.slice_gain:
                stacks = with_shading(stacks, rng, args.shading, args.slice_gain)
            (predictions,), prepared, _ = run_acquisition(stacks, est, 100, True)
            if args.midline and vol.name not in midlines:
                midlines[vol.name] = about_centre(midline_offset(vol), vol.centre)
            mid = midlines.get(vol.name)
            body = {"stacks": stack_objects(predictions)}
            masks = [p.slices.to_stack(p.slices.masks) for p in prepared]
            corrected = bias_corrected_stacks([s.volume for s in stacks], masks)   # as a job's worker does
            for name in variants:
                variant, _, share = name.partition("@")
                poses = starting_poses(body, float(share or shares[0]),
                                       keep_signal_lost=variant == "job-with-signal-lost")
                if args.start == "truth":
                    poses = [(s.atlas_from_voxel, inc) for s, (_, inc) in zip(stacks, poses)]
                volumes = [s.volume for s in stacks] if variant.startswith("job-raw-stacks") else corrected
                inputs = [(v, m, mats, inc) for v, m, (mats, inc) in zip(volumes, masks, poses)]
                ss = SliceSet.from_stacks(inputs)
                if name == variants[0]:
                    rows["predicted"].append(errors(stacks, prepared, ss.atlas_from_voxel, plane, mid))
                t = time.perf_counter()
                config = ReconstructionConfig(symmetry_plane_x_mm=plane, **VARIANTS[variant])
                if variant in JOBS:
                    res = reconstruct_never_worse(ss, args.resolution, args.rounds, config=config, **JOBS[variant])
                    left_out = place_left_out(ss, res.atlas_from_voxel_final, res.included, expected_errors(body),
                                              plane_x_mm=plane, volume=VolumeReference.of(res, inputs),
                                              starting=None if variant == "job-path-left-out" else ss.atlas_from_voxel)
                    res = replace(res, atlas_from_voxel_final=left_out.poses)
                    print("  " + left_out_changes(stacks, prepared, ss.atlas_from_voxel, res.included, left_out, plane),
                          flush=True)
                else:
                    res = reconstruct(ss, resolution_mm=args.resolution, svr_iterations=args.rounds, config=config)
                seconds[name].append(time.perf_counter() - t)
                rows[name].append(errors(stacks, prepared, res.atlas_from_voxel_final, plane, mid))
                held[name].append(res.quality["leave_one_stack_out"]["median_ncc"])
                psnr[name].append(psnrs(res, vol, stacks, prepared, mid))
                if variant in JOBS:
                    print(f"  {name} path: {res.quality['path']} {res.quality['paths']}, output pass "
                          f"{res.quality.get('output_pass')}; "
                          f"{int(ss.include.sum())} slices start included", flush=True)
                if args.atlas_frame:
                    frame = atlas_frame(res.volume, est, plane, held_out_ncc=held_out_score(res))
                    framed_res = with_frame(res, frame)
                    centred = with_frame(framed_res, midline_fit(framed_res.volume, plane, held_out_score(res)))
                    for label, moved in ((f"{name}, atlas frame", framed_res),
                                         (f"{name}, atlas frame and midline", centred)):
                        rows[label].append(errors(stacks, prepared, moved.atlas_from_voxel_final, plane, mid))
                        psnr[label].append(psnrs(moved, vol, stacks, prepared, mid))
            print(f"{level} {a}: " + ", ".join(f"{k} " + " / ".join(f"{r.mean():.2f}" for r in v[-1])
                                              for k, v in rows.items())
                  + "; leave-one-stack-out NCC " + ", ".join(f"{k} {v[-1]}" for k, v in held.items())
                  + "; PSNR, NCC " + ", ".join(f"{k} " + " / ".join(f"{x:.2f}" for x in v[-1])
                                               for k, v in psnr.items()), flush=True)
        means = {k: np.concatenate(v, axis=1).mean(axis=1) for k, v in rows.items()}
        before = np.array([r[1].mean() for r in rows["predicted"]])
        worse = {k: int(np.sum(np.array([r[1].mean() for r in rows[k]]) > before)) for k in variants}
        summary = ", ".join(f"{k} " + " / ".join(f"{x:.2f}" for x in m) + " mm" for k, m in means.items())
        times = ", ".join(f"{k} {np.mean(v):.1f} s" for k, v in seconds.items())
        ways = "as placed / frame-free" + (" / against the midline-placed truth" if args.midline else "")
        summary += (f"; PSNR (dB) {ways}; NCC {ways}: " + ", ".join(f"{k} " + " / ".join(f"{x:.2f}" for x in np.mean(v, axis=0))
                                                      for k, v in psnr.items()))
        print(f"== {level} ({args.per_level} acquisitions, {args.resolution} mm, {args.rounds} rounds; mean E.D. "
              f"against the truth / twin-min / the truth in the acquisition's own frame"
              f"{' / twin-min against the midline-placed truth' if args.midline else ''}): {summary}; "
              f"acquisitions worse than predicted (twin-min): {worse}; reconstruction {times}", flush=True)


if __name__ == "__main__":
    main()
