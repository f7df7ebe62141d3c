"""One noisy stack among clean ones: how the request places it, and how its accept flags judge it.

Per held-out volume (two acquisitions each, ``scanner_sweep.py``'s draws and its 128 mm field of
view, 1 mm pixels, 3 mm slices), the same acquisition three times: every stack at the benchmarks'
3 % Rician noise, stack ``--stack`` alone at ``--noise``, and every stack at ``--noise`` (the draws
are the same; only the noise differs). Printed for that stack in each: its slices' mean and median
E.D. against the truth, the share accepted (of all, of those over 10 mm, of those under 5 mm),
RMS E.D. over RMS expected error, its input noise and what the noise error added.

    .venv/bin/python model_export/experiments/noise_mixed.py --noise 0.20 --stack 2    # needs ../shared/data
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes, split  # noqa: E402
from model_export.calibrate_noise import acquire  # noqa: E402
from model_export.evaluate_acquisitions import MIN_MASK_PIXELS, run_acquisition  # noqa: E402
from service.pipeline.documents import stack_objects  # noqa: E402
from service.geometry.anchors import ed  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator  # noqa: E402
from service.inference.model_file import load_model  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", type=Path, default=Path("service/models/default/model.onnx"))
    ap.add_argument("--root", type=Path, default=DEFAULT_ATLAS_ROOT)
    ap.add_argument("--level", default="mild")
    ap.add_argument("--noise", type=float, default=0.20)
    ap.add_argument("--stack", type=int, default=2, help="0 axial, 1 coronal, 2 sagittal")
    ap.add_argument("--per-volume", type=int, default=2)
    ap.add_argument("--seed", type=int, default=5)
    args = ap.parse_args()
    estimator = OnnxPoseEstimator(load_model(args.model))
    volumes = load_volumes(split(args.root)[1], args.root)
    rows: dict[str, list] = {"all clean": [], "one noisy": [], "all noisy": []}
    for a, vol in enumerate(volumes * args.per_volume):
        clean = acquire(vol, np.random.default_rng([args.seed, a]), args.level)
        noisy = acquire(vol, np.random.default_rng([args.seed, a]), args.level, noise=args.noise)
        one = [noisy[i] if i == args.stack else s for i, s in enumerate(clean)]
        for name, stacks in (("all clean", clean), ("one noisy", one), ("all noisy", noisy)):
            (predictions,), prepared, truth = run_acquisition(stacks, estimator)
            answer, p = stack_objects(predictions)[args.stack], prepared[args.stack]
            keep = p.prepared.mask_pixels >= MIN_MASK_PIXELS
            final = np.array([s["atlas_from_voxel"] for s in answer["slices"]]) @ np.linalg.inv(p.network_from_voxel())
            rows[name].append((ed(final[keep], truth[args.stack][keep]),
                               np.array([s["expected_error_mm"] or np.nan for s in answer["slices"]], np.float64)[keep],
                               np.array([s["accepted"] for s in answer["slices"]])[keep],
                               answer["noise"]["input_noise"], answer["noise"]["expected_error_added_mm"]))
    print("| request | mean / median E.D. | accepted: all, > 10 mm (slices), < 5 mm | RMS E.D. / RMS expected "
          "| input noise | added |\n|---|---|---|---|---|---|")
    for name, got in rows.items():
        e, x, ok = (np.concatenate([g[k] for g in got]) for k in range(3))
        have, bad = np.isfinite(x), e > 10
        ratio = np.sqrt(np.mean(e[have] ** 2)) / np.sqrt(np.mean(x[have] ** 2))
        print(f"| {name} | {e.mean():.2f} / {np.median(e):.2f} mm | {ok.mean():.0%}, "
              f"{ok[bad].mean() if bad.any() else float('nan'):.0%} ({bad.sum()}), {ok[e < 5].mean():.0%} | {ratio:.2f} "
              f"| {np.median([g[3] for g in got]):.3f} | {np.median([g[4] for g in got]):.2f} mm |")


if __name__ == "__main__":
    main()
