"""An equal-budget comparison of the six backbones of the paper (its Table II, at small width).

Each backbone is trained with the same simulated data stream, steps, batch and learning rate, then
evaluated on the same validation slices (deterministic pass): mean anchor-point E.D., its median,
the geodesic distance, with the 3-MAD outlier rule, and the training time and inference speed.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from model_export.atlas import DEFAULT_ATLAS_ROOT, validation_volumes
from model_export.packaging import load_checkpoint
from model_export.train import pose_errors, predict_poses, train, validation_set
from model_export.train_config import TrainConfig
from service.geometry import se3

PAPER_BACKBONES = ("caffenet", "googlenet", "inception_v4", "nin", "resnet", "vgg")


def compare(out_dir: Path, backbones: tuple[str, ...] = PAPER_BACKBONES, *, steps: int = 300, batch: int = 32,
            width: float = 0.25, lr: float = 1e-3, root: Path = DEFAULT_ATLAS_ROOT) -> list[dict]:
    """Train each backbone for ``steps`` and evaluate; writes ``out_dir/table.json`` and returns the rows."""
    rows = []
    val = None
    for name in backbones:
        cfg = TrainConfig(backbone=name, width=width, steps=steps, batch=batch, lr=lr, dropout=0.25,
                          val_every=steps, val_per_volume=60, seed=0)
        t0 = time.perf_counter()
        best = train(cfg, out_dir / name, root, progress=False)
        seconds = time.perf_counter() - t0
        model, ck = load_checkpoint(best)
        if val is None:
            val = validation_set(validation_volumes(ck), root, 60)
        torch.set_num_threads(2)
        t1 = time.perf_counter()
        pred = predict_poses(model, val.inputs)
        speed = len(val.inputs) / (time.perf_counter() - t1)
        err = pose_errors(pred, val.poses)
        inl = ~se3.mad_outliers(err["gd_twin"])
        rows.append({"backbone": name, "width": width, "steps": steps, "batch": batch,
                     "parameters_m": sum(p.numel() for p in model.parameters()) / 1e6,
                     "train_s": round(seconds, 1), "ed_mean_mm": float(err["ed_mm"].mean()),
                     "ed_median_mm": float(np.median(err["ed_mm"])), "gd_mean": float(err["gd"].mean()),
                     "ed_twin_mean_mm": float(err["ed_twin_mm"].mean()),
                     "ed_twin_median_mm": float(np.median(err["ed_twin_mm"])),
                     "gd_twin_mean": float(err["gd_twin"].mean()),
                     "ed_twin_inliers_mm": float(err["ed_twin_mm"][inl].mean()), "outliers": float(1 - inl.mean()),
                     "slices_per_s": round(speed, 1)})
        (out_dir / "table.json").write_text(json.dumps(rows, indent=2))
    return rows


def markdown(rows: list[dict]) -> str:
    head = ("| backbone | params (M) | train (s) | E.D. mean (mm), truth / twin-min | E.D. median | G.D. | "
            "twin-min E.D. of the inliers | 3-MAD outliers (twin-min G.D.) | slices/s |\n"
            "|---|---|---|---|---|---|---|---|---|\n")
    return head + "\n".join(
        f"| {r['backbone']} | {r['parameters_m']:.2f} | {r['train_s']:.0f} | {r['ed_mean_mm']:.1f} / "
        f"{r.get('ed_twin_mean_mm', float('nan')):.1f} | {r['ed_median_mm']:.1f} / {r.get('ed_twin_median_mm', float('nan')):.1f} | "
        f"{r['gd_mean']:.1f} / {r.get('gd_twin_mean', float('nan')):.1f} | "
        f"{r.get('ed_twin_inliers_mm', float('nan')):.1f} | {100 * r['outliers']:.0f} % | {r['slices_per_s']:.0f} |"
        for r in rows)
