"""Test-time views (``service/inference/views.py``): accuracy and cost of 1, 4 and 8 views at the
same 100 MC samples, on single validation slices (3 mm, noisy, any orientation; whole held-out
volumes), for one or more training checkpoints. Needs ``../shared/data``.

Accuracy goes through the export path in torch (``model_export.calibrate.mc_statistics``, the
service's statistics); the cost is the service's ONNX estimator on the same slices, as a ratio to
one view measured in the same run.

    .venv/bin/python model_export/experiments/views_bench.py service/models/default/checkpoint.pt [more.pt ...] [--per-volume 60]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks.timing import alternated  # noqa: E402
from model_export.atlas import DEFAULT_ATLAS_ROOT  # noqa: E402
from model_export.calibrate import mc_statistics
from model_export.pose_metrics import auroc  # noqa: E402
from model_export.packaging import export_checkpoint, load_checkpoint  # noqa: E402
from model_export.simulate import SimulationConfig  # noqa: E402
from model_export.train import pose_errors, validation_set  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator  # noqa: E402
from service.inference.model_file import load_model  # noqa: E402

VIEWS = (1, 4, 8)


def accuracy(path: Path, per_volume: int) -> np.ndarray:
    model, ck = load_checkpoint(path)
    sim = SimulationConfig(**{k: v for k, v in ck["simulation"].items() if k in SimulationConfig.__dataclass_fields__})
    val = validation_set(ck["config"]["val_volumes"], DEFAULT_ATLAS_ROOT, per_volume, seed=2024, config=sim)
    print(f"\n{path} ({len(val.inputs)} slices of {', '.join(ck['config']['val_volumes'])}):")
    print("| views | twin-min mean / median / p90 (mm) | < 10 mm | E.D. vs truth | AUROC variance | AUROC spread |")
    print("|---|---|---|---|---|---|")
    for views in VIEWS:
        torch.manual_seed(1)
        est = mc_statistics(model, val.inputs, 100, views=views)
        e = pose_errors(est.mean, val.poses, float(ck["config"].get("plane_x_mm", 0.0)))
        err = e["ed_twin_mm"]
        print(f"| {views} | {err.mean():.2f} / {np.median(err):.2f} / {np.percentile(err, 90):.1f} | "
              f"{100 * (err < 10).mean():.1f} % | {e['ed_mm'].mean():.1f} | {auroc(est.variance, err > 10):.3f} | "
              f"{auroc(est.spread_mm, err > 10):.3f} |", flush=True)
    return val.inputs


def cost(path: Path, inputs: np.ndarray, repeats: int = 3) -> None:
    from model_export.spread import write_metadata

    onnx = Path(tempfile.mkdtemp()) / "model.onnx"
    export_checkpoint(path, onnx, name="bench", version="0", variance_threshold=1.0)
    estimators = {}
    for views in VIEWS:                                  # each view count its own file: the metadata is read once
        view_file = onnx.with_name(f"model-{views}.onnx")
        shutil.copyfile(onnx, view_file)
        write_metadata(view_file, {"tta_views": views})
        estimators[views] = OnnxPoseEstimator(load_model(view_file, threads=1))
    times = alternated({views: (lambda est=est: est.estimate(inputs, 100)) for views, est in estimators.items()},
                       repeats)
    print(f"\nONNX estimator, {len(inputs)} slices, MC-100, 1 thread, best of {repeats}, alternated: " + ", ".join(
        f"{v} view{'s' if v > 1 else ''} {1000 * t:.0f} ms ({t / times[1]:.2f}x)" for v, t in times.items()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoints", nargs="+", type=Path)
    ap.add_argument("--per-volume", type=int, default=60)
    args = ap.parse_args()
    torch.set_num_threads(1)
    inputs = None
    for path in args.checkpoints:
        inputs = accuracy(path, args.per_volume)
    cost(args.checkpoints[-1], inputs[:132])


if __name__ == "__main__":
    main()
