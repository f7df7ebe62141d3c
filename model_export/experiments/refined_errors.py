"""Per-slice errors of a job's refined poses against the truth, with what the job knows of each slice:
the table the refined poses' expected errors are fitted on, and their calibration.

For each motion level, acquisitions of the validation volumes are predicted by the shipped model as
the server does, then run through what a reconstruction job runs (the never-worse paths, the
left-out slices placed, the atlas frame and the midline; :mod:`service.jobs.worker`). Saved per
slice (``--out``, an ``.npz``): the level, the acquisition, the slice's role in the job
(:data:`ROLES`), its predicted expected error, its NCC with the job's volume at its final pose (every
slice by one measure) and the median of the slices in the volume, its leave-one-stack-out NCC, its
robust weight, its brain area, the acquisition's leave-one-stack-out median and the job's path, and
its E.D. against the truth, twin-min and in the acquisition's own frame. ``--score`` prints, per
table and level, RMS E.D. over RMS ``refined_expected_error_mm``
(:mod:`service.reconstruction.pose_errors`) and its AUROC for an E.D. over 5 mm; with ``--fit``,
the constants least squares puts on the first table. Needs ``../shared/data``. Run:
``.venv/bin/python model_export/experiments/refined_errors.py --per-level 8 --seed 5 --out seed5.npz``, then
``... --score seed5.npz seed7.npz --fit``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.acquisitions import simulate_acquisition
from model_export.pose_metrics import auroc
from model_export.evaluate_acquisitions import run_acquisition
from model_export.experiments.refine_bench import network_poses, to_truth_frame, validation_setup
from service.pipeline.documents import stack_objects
from service.geometry import twin
from service.geometry.anchors import ed
from service.jobs.uploaded_poses import expected_errors
from service.jobs.starting_poses import starting_poses
from service.reconstruction.job import refine_job
from service.reconstruction.left_out import MIN_AREA_MM2
from service.reconstruction.held_out import held_out_score
from service.reconstruction.pose_errors import (
    IN_VOLUME,
    LEFT_OUT,
    NCC_RATIO,
    PLACED_BY_STACK_MOTION,
    PLACED_BY_VOLUME,
    refined_expected_errors,
)
from service.reconstruction.slices import SliceSet

MIN_MASK_PIXELS_MM2 = 31.0
"""Slices scored: a brain section of at least 20 pixels of 1.25 mm (``evaluate_acquisitions.MIN_MASK_PIXELS``)."""
ROLES = ("in_volume", "placed_by_stack_motion", "placed_by_volume", "left_out", "not_posed")
"""A slice's role in the job, the ``role`` column's values (indices; the first four are
:func:`~service.reconstruction.pose_errors.roles`)."""


def job_slices(stacks, prepared, body: dict, est, plane: float, resolution: float, rounds: int) -> dict:  # noqa: ANN001
    """Every slice's columns for one acquisition (module docstring) and the job's path."""
    masks = [p.slices.to_stack(p.slices.masks) for p in prepared]
    inputs = [(s.volume, m, mats, inc) for s, m, (mats, inc) in zip(stacks, masks, starting_poses(body))]
    expected = expected_errors(body)
    job = refine_job(SliceSet.from_stacks(inputs), inputs, expected, estimator=est, plane_x_mm=plane,
                     resolution_mm=resolution, svr_iterations=rounds)
    res, ncc = job.result, job.left_out.ncc
    pose, true = network_poses(stacks, prepared, res.atlas_from_voxel_final)
    role = np.where((job.role == LEFT_OUT) & ~np.isfinite(expected), ROLES.index("not_posed"), job.role)
    frame = to_truth_frame(pose[res.included], true[res.included])
    held, n = held_out_score(res), len(pose)
    return {"role": role, "expected": expected, "ncc": ncc,
            "placed_ncc": np.full(n, np.nanmedian(ncc[res.included]) if res.included.any() else np.nan),
            "held_out_ncc": res.held_out_ncc if res.held_out_ncc is not None else np.full(n, np.nan),
            "weight": np.where(res.included, res.slice_weight, 0.0), "area_mm2": job.areas_mm2,
            "loso": np.full(n, held if held is not None else np.nan),
            "ed": ed(pose, true), "twin_min": twin.twin_min_ed(pose, true, plane), "own_frame": ed(frame @ pose, true),
            "path": np.full(n, str(res.quality.get("path")))}


def model_errors(t: dict) -> np.ndarray:
    """The shipped model's refined expected errors for a table's rows (one job at a time)."""
    out = np.full(len(t["role"]), np.nan)
    for a in np.unique(t["acquisition"]):
        s = t["acquisition"] == a
        loso = float(t["loso"][s][0])
        out[s] = refined_expected_errors(t["role"][s], t["ncc"][s], t["area_mm2"][s], t["expected"][s],
                                         held_out_ncc=loso if np.isfinite(loso) else None)
    return out


def fit_terms(t: dict) -> np.ndarray:
    """``[n, 5]`` the model's squared terms per row, each with a unit constant (their least-squares
    weights on the placed slices' squared E.D. are the constants squared): 1, placed beside the volume,
    the prediction's error of a slice in the volume, the NCC shortfall for a large and for a small section."""
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.nan_to_num(t["ncc"] / t["placed_ncc"], nan=NCC_RATIO)
    short = np.maximum(NCC_RATIO - ratio, 0.0)
    large = t["area_mm2"] >= MIN_AREA_MM2
    inside = t["role"] == IN_VOLUME
    return np.stack([np.ones(len(ratio)), ~inside, np.nan_to_num(t["expected"]) ** 2 * inside,
                     short ** 2 * large, short ** 2 * ~large], 1).astype(np.float64)


def score(tables: list[Path], fit: bool) -> None:
    """Per level: RMS E.D. / RMS expected error of the refined poses (the shipped model, and the
    prediction's expected errors for comparison), per role and over every posed slice; the AUROC of
    each for E.D. > 5 mm. With ``fit``, the constants least squares puts on the first table."""
    from scipy.optimize import nnls
    for i, path in enumerate(tables):
        t = dict(np.load(path))
        posed = (t["area_mm2"] >= MIN_MASK_PIXELS_MM2) & np.isfinite(t["expected"])
        if fit and i == 0:
            placed = posed & (t["role"] != LEFT_OUT)
            weights, _ = nnls(fit_terms(t)[placed], t["ed"][placed] ** 2)
            print("least squares (square roots): frame, beside, predicted share, shortfall large / small:",
                  " / ".join(f"{w:.2f}" for w in np.sqrt(weights)))
        model = model_errors(t)
        rms = lambda x: float(np.sqrt(np.mean(np.square(x))))  # noqa: E731
        for level in dict.fromkeys(t["level"]):
            cells = []
            for name, which in (("in the volume", (IN_VOLUME,)),
                                ("placed beside it", (PLACED_BY_STACK_MOTION, PLACED_BY_VOLUME)),
                                ("left out", (LEFT_OUT,)), ("every posed slice", range(LEFT_OUT + 1))):
                s = posed & (t["level"] == level) & np.isin(t["role"], which)
                if s.any():
                    cells.append(f"{name} ({s.sum()}) {rms(t['ed'][s]):.2f} / {rms(model[s]):.2f} = "
                                 f"{rms(t['ed'][s]) / rms(model[s]):.2f}")
            s = posed & (t["level"] == level)
            cells.append(f"with the prediction's expected errors {rms(t['ed'][s]) / rms(t['expected'][s]):.2f}")
            print(f"{path.name} {level}: RMS E.D. / RMS expected: " + "; ".join(cells))
        bad = t["ed"][posed] > 5.0
        print(f"{path.name} AUROC for E.D. > 5 mm: refined {auroc(model[posed], bad):.3f}, "
              f"the prediction's {auroc(t['expected'][posed], bad):.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="service/models/default/model.onnx")
    ap.add_argument("--levels", default="mild,moderate,jumps,independent")
    ap.add_argument("--per-level", type=int, default=8)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--resolution", type=float, default=1.5)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", type=Path, help="collect a table into this .npz")
    ap.add_argument("--score", type=Path, nargs="*", default=[], help="score the shipped model on these tables")
    ap.add_argument("--fit", action="store_true", help="with --score: least squares on the first table")
    args = ap.parse_args()
    if args.score:
        return score(args.score, args.fit)
    if args.out is None:
        ap.error("give --out (collect) or --score (score tables)")
    est, plane, vols = validation_setup(args.model)
    rng = np.random.default_rng(args.seed)
    table: dict[str, list] = {}
    for level in args.levels.split(","):
        for a in range(args.per_level):
            t = time.perf_counter()
            vol = vols[a % len(vols)]
            stacks = simulate_acquisition(vol.image, vol.mask, vol.affine, rng, level)
            (predictions,), prepared, _ = run_acquisition(stacks, est, 100, True)
            cols = job_slices(stacks, prepared, {"stacks": stack_objects(predictions)}, est, plane,
                              args.resolution, args.rounds)
            n = len(cols["role"])
            cols.update(level=np.full(n, level), acquisition=np.full(n, f"{level}-{a}"), volume=np.full(n, vol.name))
            for k, v in cols.items():
                table.setdefault(k, []).append(np.asarray(v))
            means = {r: cols["ed"][cols["role"] == i].mean() for i, r in enumerate(ROLES) if (cols["role"] == i).any()}
            print(f"{level} {a} {vol.name}: path {cols['path'][0]}, " + ", ".join(f"{r} {m:.2f}" for r, m in means.items())
                  + f" mm; {time.perf_counter() - t:.0f} s", flush=True)
            np.savez(args.out, **{k: np.concatenate(v) for k, v in table.items()})


if __name__ == "__main__":
    main()
