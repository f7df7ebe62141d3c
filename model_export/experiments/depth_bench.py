"""Single-slice error by depth: where along its normal a plane cuts the brain, over the whole extent.

The standard validation (and the paper) keeps planes in the central 70 % of the brain; a real stack
covers all of it. Validation slices are drawn over the full extent here (``tz_fraction = 0.5``), and
the twin-min E.D. is reported per band of ``|Tz - middle| / half-extent``, for each checkpoint, through
the export path with the service's statistics and test-time views. Needs ``../shared/data``.

    .venv/bin/python model_export/experiments/depth_bench.py service/models/default/checkpoint.pt [more.pt ...] [--views 8]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes  # noqa: E402
from model_export.calibrate import mc_statistics  # noqa: E402
from model_export.packaging import load_checkpoint  # noqa: E402
from model_export.simulate import SimulationConfig  # noqa: E402
from model_export.train import pose_errors, validation_set  # noqa: E402

BANDS = ((0.0, 0.35), (0.35, 0.7), (0.7, 0.85), (0.85, 1.0))


def relative_depth(poses: np.ndarray, names: list[str], volumes: dict) -> np.ndarray:
    """``|Tz - middle| / half-extent`` of each plane in its volume (0 = middle, 1 = the brain's edge)."""
    names = np.asarray(names)
    out = np.empty(len(poses))
    for name, vol in volumes.items():
        mine = names == name
        if mine.any():
            out[mine] = vol.relative_depth(poses[mine])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoints", nargs="+", type=Path)
    ap.add_argument("--per-volume", type=int, default=80)
    ap.add_argument("--views", type=int, default=8)
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(f"twin-min E.D. (mm) of single slices over the full extent, MC-100 over {args.views} views; "
          "bands of |Tz - middle| / half-extent:")
    print("| checkpoint | " + " | ".join(f"{lo:.2f}-{hi:.2f}" for lo, hi in BANDS) + " | all |")
    print("|---|" + "---|" * (len(BANDS) + 1))
    for path in args.checkpoints:
        model, ck = load_checkpoint(path)
        names = ck["config"]["val_volumes"]
        sim = SimulationConfig(**{k: v for k, v in ck["simulation"].items() if k in SimulationConfig.__dataclass_fields__})
        val = validation_set(names, DEFAULT_ATLAS_ROOT, args.per_volume, seed=99,
                             config=dataclasses.replace(SimulationConfig.validation(size=sim.size, pixel_mm=sim.pixel_mm),
                                                        tz_fraction=0.5))
        rel = relative_depth(val.poses, val.volume, {v.name: v for v in load_volumes(names, DEFAULT_ATLAS_ROOT)})
        torch.manual_seed(1)
        est = mc_statistics(model, val.inputs, 100, plane_x_mm=float(ck["config"].get("plane_x_mm", 0.0)),
                            views=args.views)
        err = pose_errors(est.mean, val.poses, float(ck["config"].get("plane_x_mm", 0.0)))["ed_twin_mm"]
        cells = [f"{err[(rel >= lo) & (rel < hi)].mean():.1f} (n={int(((rel >= lo) & (rel < hi)).sum())})"
                 for lo, hi in BANDS]
        print(f"| {path} | " + " | ".join(cells) + f" | {err.mean():.1f} |", flush=True)


if __name__ == "__main__":
    main()
