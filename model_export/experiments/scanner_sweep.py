"""``/v1/predict``'s accuracy on acquisitions as other scanners write them: pixel sizes, slice thicknesses, noise.

The acquisition benchmarks simulate 1 mm pixels and 3 mm slices 3 mm apart. Scanners write
0.5-1.6 mm pixels and 2-5 mm slices, some overlapping (4 mm thick, 2 mm apart), and a low-field
scanner's stacks are noisier (Rician noise of 8 or 15 % of the bright end). This script runs the
same held-out volumes, motion level and seed through the whole pipeline (masks uploaded, N4, 100 MC
samples, every stage) once per acquisition setting, and prints per setting the mean E.D. against the
truth and twin-min, the median, the slices with brain, the shares of slices with E.D. < 5 mm and
> 10 mm that are accepted, and the stacks' median input noise (:func:`~service.preprocess.noise.input_noise`,
what a ``/v1/predict`` answer's ``noise`` reports). Every setting keeps a 128 mm field of view. Each acquisition draws from its
own seed, so that its first stack's placement and motion are alike in every setting (later draws
follow the image sizes).

Also a signal void: a dark ball in the brain (:func:`with_void`), which the acquisition simulations
never make; its slices are split by the share of their brain it darkened (:func:`void_split`), the
network's own twin-min E.D. beside the final one, which tells the network's part from the stages'.

``--dump F.npz`` keeps every setting's per-slice columns (with each slice's stack's input noise);
``--smooth T`` smooths noisy stacks before the network (:func:`noise_offset.smoothing`).

    .venv/bin/python model_export/experiments/scanner_sweep.py [--levels mild,jumps] [--per-volume 2] [--only 1,9] [--model M]   # needs ../shared/data
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.acquisitions import SimulatedStack  # noqa: E402
from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes, split  # noqa: E402
from model_export.calibrate_acceptance import rates, rms, share  # noqa: E402
from model_export.calibrate_noise import acquire  # noqa: E402
from model_export.evaluate_acquisitions import MIN_MASK_PIXELS, Scored, run_acquisition, score  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator  # noqa: E402
from service.inference.model_file import load_model  # noqa: E402
from service.io.volume import Volume  # noqa: E402
from service.preprocess.stack import stack_axis  # noqa: E402

THREE_MM = {"thickness_mm": 3.0, "gap_mm": 3.0}
SETTINGS: dict[str, tuple[dict[str, float], str | None]] = {
    "1.0 mm pixels, 3 mm slices (the benchmarks')": ({"pixel_mm": 1.0, **THREE_MM}, None),
    "0.5 mm pixels": ({"pixel_mm": 0.5, **THREE_MM}, None),
    "0.8 mm pixels": ({"pixel_mm": 0.8, **THREE_MM}, None),
    "1.25 mm pixels": ({"pixel_mm": 1.25, **THREE_MM}, None),
    "1.6 mm pixels": ({"pixel_mm": 1.6, **THREE_MM}, None),
    "2 mm slices": ({"pixel_mm": 1.0, "thickness_mm": 2.0, "gap_mm": 2.0}, None),
    "4.5 mm slices": ({"pixel_mm": 1.0, "thickness_mm": 4.5, "gap_mm": 4.5}, None),
    "4 mm slices 2 mm apart": ({"pixel_mm": 1.0, "thickness_mm": 4.0, "gap_mm": 2.0}, None),
    "1.5 mm slices": ({"pixel_mm": 1.0, "thickness_mm": 1.5, "gap_mm": 1.5}, None),
    "3 mm slices 1.5 mm apart": ({"pixel_mm": 1.0, "thickness_mm": 3.0, "gap_mm": 1.5}, None),
    "a signal void in the brain (with_void)": ({"pixel_mm": 1.0, **THREE_MM}, "void"),
    "Rician noise 8 % (the benchmarks' 3 %)": ({"pixel_mm": 1.0, **THREE_MM, "noise": 0.08}, None),
    "Rician noise 15 % (a low-field scanner's)": ({"pixel_mm": 1.0, **THREE_MM, "noise": 0.15}, None),
    "0.8 mm pixels, noise 15 %": ({"pixel_mm": 0.8, **THREE_MM, "noise": 0.15}, None),
    "1.6 mm pixels, noise 8 %": ({"pixel_mm": 1.6, **THREE_MM, "noise": 0.08}, None),
    "1.6 mm pixels, noise 15 %": ({"pixel_mm": 1.6, **THREE_MM, "noise": 0.15}, None),
    "gamma 0.5 (the training draws 0.75-1.35)": ({"pixel_mm": 1.0, **THREE_MM}, "gamma 0.5"),
    "gamma 2": ({"pixel_mm": 1.0, **THREE_MM}, "gamma 2"),
    "tissue contrast halved (a balanced-SSFP look)": ({"pixel_mm": 1.0, **THREE_MM}, "tissue contrast halved"),
}
"""Each setting's :func:`~model_export.calibrate_noise.acquire` keywords, and how its stacks are rewritten: ``"void"``
(:func:`with_void`), a key of :data:`CONTRASTS` (:func:`with_contrast`) or not at all."""
VOID_RADIUS_MM, VOID_OFFSET_MM, VOID_GAIN = 25.0, 15.0, 0.4
"""A dark ball in the scanner, as 3 T dielectric shading leaves one in some real stacks (a real
whole-uterus stack of another site shows the head 0.35-0.5x its median over a third of the brain):
the signal times :data:`VOID_GAIN` within :data:`VOID_RADIUS_MM` of a point :data:`VOID_OFFSET_MM`
from the brain's centre, smoothly (a 3 mm edge)."""


def with_void(stacks: list[SimulatedStack], rng: np.random.Generator) -> list[SimulatedStack]:
    """The stacks of one acquisition with one dark ball in the scanner (the same for every stack)."""
    brain = [s.volume.affine @ np.append(np.argwhere(s.mask.array).mean(0), 1.0) for s in stacks]
    direction = rng.normal(size=3)
    centre = np.mean(brain, axis=0)[:3] + VOID_OFFSET_MM * direction / np.linalg.norm(direction)
    out = []
    for s in stacks:
        ijk = np.indices(s.volume.array.shape).reshape(3, -1).T
        r = np.linalg.norm(ijk @ s.volume.affine[:3, :3].T + s.volume.affine[:3, 3] - centre, axis=1)
        gain = VOID_GAIN + (1 - VOID_GAIN) / (1 + np.exp(-(r - VOID_RADIUS_MM) / 1.5))
        dark = (s.volume.array * gain.reshape(s.volume.array.shape)).astype(np.float32)
        out.append(replace(s, volume=Volume(dark, s.volume.affine)))
    return out


LOSS_RUN = (0.25, 0.6)
LOSS_GAIN = (0.1, 0.35)
LOSS_NOISE = 0.05


def with_signal_loss(stacks: list[SimulatedStack], rng: np.random.Generator) -> list[SimulatedStack]:
    """The stacks of one acquisition with a signal loss over the brain in a run of consecutive slices
    of each (as a real whole-uterus stack shows it: the brain's inside dark and noisy in a third to
    a half of its slices): in :data:`LOSS_RUN` of the slices with brain, from a random start, the
    brain's voxels times a gain of :data:`LOSS_GAIN` plus Gaussian noise of :data:`LOSS_NOISE` of the
    brain's 99th percentile."""
    out = []
    for s in stacks:
        axis = stack_axis(s.volume)
        mask = s.mask.array > 0
        with_brain = np.flatnonzero(np.moveaxis(mask, axis, 0).reshape(mask.shape[axis], -1).any(1))
        if len(with_brain) < 4:
            out.append(s)
            continue
        n = max(2, int(round(rng.uniform(*LOSS_RUN) * len(with_brain))))
        start = int(rng.integers(0, len(with_brain) - n + 1))
        top = float(np.percentile(s.volume.array[mask], 99))
        array = np.moveaxis(np.array(s.volume.array, np.float32), axis, 0)
        inside = np.moveaxis(mask, axis, 0)
        for k in with_brain[start:start + n]:
            m = inside[k]
            array[k][m] = array[k][m] * rng.uniform(*LOSS_GAIN) + rng.normal(0, LOSS_NOISE * top, m.sum())
        array = np.clip(np.moveaxis(array, 0, axis), 0, None).astype(np.float32)
        out.append(replace(s, volume=Volume(array, s.volume.affine)))
    return out



def with_shading(stacks: list[SimulatedStack], rng: np.random.Generator, field: float,
                 gain_sd: float = 0.0) -> list[SimulatedStack]:
    """The stacks of one acquisition with intensities a coil and a single-shot sequence change: a
    linear field over each stack, ``1 +- field`` across its brain along a random direction (another
    per stack: slices through it differ in gain and are shaded across), and each slice's own gain,
    ``exp(N(0, gain_sd))``."""
    out = []
    for s in stacks:
        axis = stack_axis(s.volume)
        mask = s.mask.array > 0
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        idx = np.indices(mask.shape).reshape(3, -1).T.astype(np.float64)
        along = (idx @ s.volume.affine[:3, :3].T) @ direction
        inside = along[mask.ravel()] if mask.any() else along
        lo, hi = float(inside.min()), float(inside.max())
        ramp = 1.0 + field * np.clip(2.0 * (along - lo) / max(hi - lo, 1e-6) - 1.0, -1.5, 1.5)
        gains = np.exp(rng.normal(0.0, gain_sd, mask.shape[axis])) if gain_sd else np.ones(mask.shape[axis])
        shape = [1, 1, 1]
        shape[axis] = -1
        array = s.volume.array * ramp.reshape(mask.shape) * gains.reshape(shape)
        out.append(replace(s, volume=Volume(np.clip(array, 0, None).astype(np.float32), s.volume.affine)))
    return out

CONTRASTS = {
    "gamma 0.5": lambda t: t ** 0.5,
    "gamma 2": lambda t: t ** 2.0,
    "tissue contrast halved": lambda t: t - 0.5 * (t - 0.45) * np.clip((0.9 - t) / 0.3, 0.0, 1.0),
}
"""Intensity curves on each stack's intensities over its brain's 99th percentile: gammas outside the
training's draws, and grey and white matter (below about 0.6) drawn halfway to 0.45 with the CSF
(0.9 and above) as it is, as a balanced-SSFP (TrueFISP) stack shows the fetal brain."""


def with_contrast(stacks: list[SimulatedStack], curve: str) -> list[SimulatedStack]:
    """The stacks with :data:`CONTRASTS` ``curve`` applied to their intensities.

    Example (a stack of brain at 0.3 and CSF at 1.0, tissue contrast halved: the CSF stays):
        >>> m = Volume(np.ones((3, 1, 1), np.uint8), np.eye(4))
        >>> s = SimulatedStack(Volume(np.array([0.3, 1.0, 1.0], np.float32).reshape(3, 1, 1), np.eye(4)), m,
        ...                    np.eye(4)[None], "axial", np.arange(1), "mild")
        >>> with_contrast([s], "tissue contrast halved")[0].volume.array.ravel().round(3).tolist()
        [0.375, 1.0, 1.0]
    """
    out = []
    for s in stacks:
        top = float(np.percentile(s.volume.array[s.mask.array > 0], 99)) if s.mask.array.any() else 1.0
        t = np.clip(s.volume.array / top, 0.0, None)
        out.append(replace(s, volume=Volume((CONTRASTS[curve](t) * top).astype(np.float32), s.volume.affine)))
    return out


DARK_GAIN = 0.7
"""A voxel the void darkened to under this fraction of its signal counts as darkened."""
DARK_SHARES = (0.0, 0.3)
"""The void's split of the slices: none of the brain darkened, under 30 % of it, 30 % or more."""


def darkened_share(clean: list[SimulatedStack], dark: list[SimulatedStack]) -> list[NDArray]:
    """Per slice of each stack, the share of its brain voxels that :func:`with_void` darkened to under
    :data:`DARK_GAIN` of their signal (slices without brain: 0).

    Example (one stack whose first slice lies in the ball, the second outside):
        >>> m = Volume(np.ones((2, 2, 2), np.uint8), np.eye(4))
        >>> clean = SimulatedStack(Volume(np.ones((2, 2, 2), np.float32), np.eye(4)), m, np.eye(4)[None], "axial", np.arange(2), "mild")
        >>> dark = replace(clean, volume=Volume(np.array([[[0.4, 1.0]] * 2] * 2, np.float32), np.eye(4)))
        >>> darkened_share([clean], [dark])[0].tolist()
        [1.0, 0.0]
    """
    out = []
    for c, d in zip(clean, dark):
        brain = c.mask.array > 0
        darkened = brain & (d.volume.array < DARK_GAIN * c.volume.array)
        out.append(darkened.sum(axis=(0, 1)) / np.maximum(brain.sum(axis=(0, 1)), 1))
    return out


def void_split(scored: Scored, share: NDArray, keep: NDArray) -> str:
    """One line: the network's twin-min E.D. and the final E.D. of the slices by how much of their
    brain the void darkened (:data:`DARK_SHARES`), and how many over 10 mm are accepted."""
    net, final, accepted = (scored.array(k) for k in ("ed_network_min", "ed", "accepted"))
    parts = []
    for name, g in (("none darkened", share <= DARK_SHARES[0]),
                    (f"under {DARK_SHARES[1]:.0%}", (share > DARK_SHARES[0]) & (share < DARK_SHARES[1])),
                    (f"{DARK_SHARES[1]:.0%} or more", share >= DARK_SHARES[1])):
        g = g & keep
        bad = g & (final > 10.0)
        parts.append(f"{name} ({g.sum()}): network {net[g].mean():.2f}, final {final[g].mean():.2f} mm, "
                     f"{(bad & accepted.astype(bool)).sum()} of {bad.sum()} over 10 mm accepted")
    return "  slices by the void's share of their brain: " + "; ".join(parts)


def calibration(error_mm: NDArray, expected_mm: NDArray) -> float:
    """RMS E.D. over RMS expected error of the slices that have an expected error (1: calibrated).

    Example:
        >>> float(calibration(np.array([3.0, 4.0, 9.0]), np.array([3.0, 4.0, np.inf])))
        1.0
    """
    have = np.isfinite(expected_mm)
    return rms(error_mm[have]) / rms(expected_mm[have]) if have.any() else float("nan")


def sweep(estimator, volumes: list, level: str, per_volume: int, seed: int,  # noqa: ANN001
          only: set[int] | None = None, dump: dict[str, NDArray] | None = None) -> list[str]:
    """One line per setting: the same volumes and random draws for each. ``dump``: gets each setting's
    per-slice columns (``<level>/<setting number>/<column>``), with each slice's stack's input noise."""
    lines = []
    for i, (name, (geometry, rewrite)) in enumerate(SETTINGS.items(), 1):
        if only and i not in only:
            continue
        scored, darkened, noise = Scored(), [], []
        start = time.perf_counter()
        for a, vol in enumerate(volumes * per_volume):
            rng = np.random.default_rng([seed, a])         # each acquisition's draws start alike in every setting
            stacks = acquire(vol, rng, level, **geometry)
            if rewrite == "void":
                clean, stacks = stacks, with_void(stacks, rng)
                darkened += darkened_share(clean, stacks)
            elif rewrite is not None:
                stacks = with_contrast(stacks, rewrite)
            (predictions,), prepared, truth = run_acquisition(stacks, estimator)
            score(predictions, prepared, truth, stacks, estimator.info.symmetry_plane_x_mm, scored)
            noise += [p.input_noise for p in prepared]
        keep = scored.array("mask_pixels") >= MIN_MASK_PIXELS
        e, t, a, x = (scored.array(k)[keep] for k in ("ed", "ed_min", "accepted", "expected"))
        shares = rates({"ed": e, "ed_min": t}, a.astype(bool))
        lines.append(f"| {name} | {e.mean():.2f} / {t.mean():.2f} mm | {np.median(e):.2f} mm | {len(e)} | "
                     f"{share(shares['good_accepted'])} | {share(shares['bad_accepted'])} ({shares['bad_slices']}) | "
                     f"{calibration(e, x):.2f} | {np.nanmedian(noise):.3f} | "
                     f"{time.perf_counter() - start:.0f} s |")
        print(lines[-1], flush=True)
        if dump is not None:
            dump.update({f"{level}/{i}/{k}": scored.array(k) for k in scored.columns if k != "orientation"})
        if rewrite == "void":
            print(void_split(scored, np.concatenate(darkened), keep), flush=True)
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", type=Path, default=Path("service/models/default/model.onnx"))
    ap.add_argument("--root", type=Path, default=DEFAULT_ATLAS_ROOT)
    ap.add_argument("--levels", default="mild,jumps")
    ap.add_argument("--per-volume", type=int, default=2)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--only", help="comma-separated setting numbers (1-based) to run")
    ap.add_argument("--dump", type=Path, help="write every setting's per-slice columns to this .npz")
    ap.add_argument("--smooth", type=float, help="smooth stacks of input noise over 0.09 down to this first "
                                                 "(an experiment: noise_offset.smoothing)")
    args = ap.parse_args()
    if args.smooth:
        import service.pipeline.prepare as prepare
        from noise_offset import smoothing

        prepare.preprocess_slices = smoothing(args.smooth)
    estimator = OnnxPoseEstimator(load_model(args.model))
    volumes = load_volumes(split(args.root)[1], args.root)
    dump: dict[str, NDArray] | None = {} if args.dump else None
    for level in args.levels.split(","):
        print(f"\n{level} motion, {len(volumes) * args.per_volume} acquisitions per setting (seed {args.seed})\n")
        print("| acquisition | mean E.D. (truth / twin-min) | median E.D. | slices | E.D. < 5 mm accepted "
              "| E.D. > 10 mm accepted (slices) | RMS E.D. / RMS expected | input noise (median) | time |")
        print("|---|---|---|---|---|---|---|---|---|")
        sweep(estimator, volumes, level, args.per_volume, args.seed,
              {int(k) for k in args.only.split(",")} if args.only else None, dump)
        if dump is not None:
            np.savez_compressed(args.dump, **dump)


if __name__ == "__main__":
    main()
