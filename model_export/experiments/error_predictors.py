"""How well can a slice's final error be predicted? AUROC of scores for E.D. > 10 mm, per motion level.

Reads the per-slice columns that ``svrnet-train calibrate-acceptance --slices FILE.npz`` (or
``evaluate --acquisitions --slices``) writes and ranks every score the service has (the MC variance,
``expected_error_mm``, the stage's expected error before the image refinement, the image mismatch
left after it, the refined pose's Laplace spread, the MC mass on the other twin, how far the stages
moved the slice, the motion the stage fitted, depth and time in the stack) against two the service
cannot have: the network's own true error and the slice's true motion (oracles: an upper reference
for what per-slice information can do). A logistic combination of the service's scores, cross-validated by stack (no stack in its
own training fold), shows what a learned predictor would add.

    .venv/bin/svrnet-train calibrate-acceptance service/models/default/model.onnx --no-write \\
        --report /tmp/acceptance.md --slices /tmp/slices.npz
    .venv/bin/python model_export/experiments/error_predictors.py /tmp/slices.npz
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.pose_metrics import auroc  # noqa: E402
from model_export.evaluate_acquisitions import ERROR_MM, MIN_MASK_PIXELS  # noqa: E402

SERVICE = ("variance", "expected", "expected_stage", "mismatch", "spread", "twin_mass", "moved_mm", "fitted_motion_mm", "depth",
           "time")
ORACLE = ("ed_network_min", "motion_mm")


def _feature(cols: dict[str, np.ndarray], key: str) -> np.ndarray:
    """One score per slice, NaN as 0 and infinity above every finite value (a column the file lacks,
    such as ``spread`` in files written before it was kept: all 0)."""
    v = np.asarray(cols.get(key, np.full(len(cols["ed"]), np.nan)), dtype=np.float64)
    big = np.nanmax(np.where(np.isfinite(v), v, np.nan)) if np.isfinite(v).any() else 0.0
    return np.nan_to_num(v, nan=0.0, posinf=10 * big + 1)


def logistic_cv(x: np.ndarray, y: np.ndarray, groups: np.ndarray, folds: int = 5, l2: float = 1e-2) -> np.ndarray:
    """Out-of-fold scores of an L2-regularised logistic regression, folds by ``groups`` (stacks)."""
    x = np.column_stack([np.log1p(np.abs(x)), np.ones(len(x))])
    out = np.zeros(len(y))
    which = np.unique(groups) % folds
    fold = which[np.searchsorted(np.unique(groups), groups)]
    for f in range(folds):
        tr, te = fold != f, fold == f
        if not te.any() or y[tr].all() or not y[tr].any():
            continue
        mu, sd = x[tr, :-1].mean(0), x[tr, :-1].std(0) + 1e-9
        z = np.column_stack([(x[:, :-1] - mu) / sd, x[:, -1]])

        def loss(w: np.ndarray, zt: np.ndarray = z[tr], yt: np.ndarray = y[tr]) -> float:
            s = zt @ w
            return float(np.mean(np.logaddexp(0.0, s) - yt * s) + l2 * w[:-1] @ w[:-1])

        w = minimize(loss, np.zeros(z.shape[1]), method="L-BFGS-B").x
        out[te] = z[te] @ w
    return out


def table(path: Path) -> list[str]:
    data = np.load(path)
    rows = sorted({k.split("/")[0] for k in data.files})
    lines = ["| motion | slices | E.D. > 10 mm | " + " | ".join(SERVICE) + " | logistic (service, CV) | "
             + " | ".join(f"oracle: {k}" for k in ORACLE) + " |",
             "|" + "---|" * (4 + len(SERVICE) + len(ORACLE))]
    for row in rows:
        cols = {k.split("/", 1)[1]: data[k] for k in data.files if k.startswith(row + "/")}
        keep = cols["mask_pixels"] >= MIN_MASK_PIXELS
        cols = {k: v[keep] for k, v in cols.items()}
        y = cols["ed"] > ERROR_MM
        if y.all() or not y.any():
            continue
        service = np.column_stack([_feature(cols, k) for k in SERVICE])
        learned = logistic_cv(service, y, cols["stack"])
        cells = [f"{auroc(_feature(cols, k), y):.2f}" for k in SERVICE] + [f"{auroc(learned, y):.2f}"]
        cells += [f"{auroc(_feature(cols, k), y):.2f}" for k in ORACLE]
        lines.append(f"| {row} | {keep.sum()} | {100 * y.mean():.1f} % | " + " | ".join(cells) + " |")
    return lines


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("columns", type=Path, help="the .npz of per-slice columns that calibrate-acceptance --slices wrote")
    print("\n".join(table(ap.parse_args().columns)))
