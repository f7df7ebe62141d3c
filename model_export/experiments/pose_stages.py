"""Where a real scan's poses with and without masks part: stage by stage, slice by slice.

The real scan (``mial_lausanne_t30``) is prepared twice with the manual masks and twice with the
localiser's (both with the 2 mm inset, ``masks_hold_csf``), each preparation's slices through the
network once. The same network statistics then go through ``/v1/predict``'s stages three times:
none (the network's poses), the stack-consistency stage with the request's pooling, and every
stage (image consistency too). Per pair of runs and stage: the median E.D. per stack between the
two answers' slice poses. Manual against manual is the floor (zero with a model's fixed draws;
other MC draws with one that draws in its graph); localiser against
localiser, the localiser's own; manual against localiser, the gap the localisation issue's
target is about. Each manual-localiser pair's difference is then split into one rigid offset of
the whole stack (about the atlas origin: a stack tilted as a whole) and what is left with it undone.
Then what the stack stage estimated of each run (the network's per-slice noise, its branch) and,
with ``--slices``, each slice's mask agreement beside its network poses' distance.
``--oracle-below D``: the localiser's mask of every slice whose Dice against the manual one is
under ``D`` is replaced by the manual mask (what the rest of the stack does once its worst
slices are masked right).

    .venv/bin/python model_export/experiments/pose_stages.py [--localiser M] [--model M] [--slices]
        [--oracle-below 0.8]                                             # needs ../shared/data/real_scans
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.experiments.frame_bias import as_row, common_frame  # noqa: E402
from model_export.localiser.evaluate import REAL_SCANS, csf_mask_upload, dice, masked_stacks, median_ed  # noqa: E402
from model_export.localiser.pose_accuracy import pose_estimator  # noqa: E402
from model_export.localiser.pose_accuracy import slice_poses  # noqa: E402
from service.pipeline.documents import stack_objects  # noqa: E402
from service.core.settings import DEFAULT_LOCALISERS_DIR  # noqa: E402
from service.geometry import anchors, twin  # noqa: E402
from service.pipeline.predict import estimate_stacks, predict_from_estimates  # noqa: E402
from service.pipeline.prepare import StackUpload, prepare_stacks  # noqa: E402
from service.preprocess.localise import Localiser  # noqa: E402

STAGES = {"network": (False, False), "stack stage, pooled": (True, False), "every stage": (True, True)}


def run(uploads: list[StackUpload], estimator) -> tuple[dict, list, list]:  # noqa: ANN001
    """One preparation and network pass; each stage's answers, the prepared stacks and the predictions
    of the stack stage."""
    info = estimator.info
    prepared = prepare_stacks(uploads, info, True, workers=2)
    parts, _ = estimate_stacks(prepared, estimator, 100)
    answers, staged = {}, None
    for stage, (stack, image) in STAGES.items():
        predictions, _ = predict_from_estimates(prepared, copy.deepcopy(parts), info, info.variance_threshold,
                                                stack, None, image)
        answers[stage] = stack_objects(predictions)
        staged = predictions if stack and not image else staged
    return answers, prepared, staged


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scan", type=Path, default=REAL_SCANS / "mial_lausanne_t30")
    ap.add_argument("--localiser", type=Path, default=DEFAULT_LOCALISERS_DIR / "default" / "model.onnx")
    ap.add_argument("--model", type=Path, help="the pose model (default: the shipped one)")
    ap.add_argument("--slices", action="store_true", help="each slice of the first pair manual/localiser")
    ap.add_argument("--oracle-below", type=float, default=0.0, help="manual masks on slices under this Dice")
    args = ap.parse_args()
    estimator = pose_estimator(args.model)
    names, volumes, masks, found = masked_stacks(args.scan, Localiser.load(args.localiser))
    if not names:
        sys.exit(f"needs stacks with manual masks in {args.scan}")
    if args.oracle_below > 0:
        found = [oracle_masks(f, m, args.oracle_below) for f, m in zip(found, masks)]
    print("Dice of the localiser's masks: " + ", ".join(f"{n} {dice(f, m):.3f}" for n, f, m in zip(names, found, masks)))

    def uploads(kind: str) -> list[StackUpload]:
        return [csf_mask_upload(n, v, m if kind == "manual" else f) for n, v, m, f in zip(names, volumes, masks, found)]

    runs = {key: run(uploads(key.split()[0]), estimator) for key in ("manual 1", "manual 2", "localiser 1", "localiser 2")}
    print("\nMedian E.D. (mm) per stack (" + " / ".join(names) + ") between two runs' answers:\n")
    print("| runs | " + " | ".join(STAGES) + " |\n|---|" + "---|" * len(STAGES))
    for a, b in (("manual 1", "manual 2"), ("localiser 1", "localiser 2"), ("manual 1", "localiser 1"),
                 ("manual 2", "localiser 2")):
        cells = [" / ".join(f"{median_ed([runs[a][0][s][j]], [runs[b][0][s][j]], [runs[a][1][j]])[0]:.1f}"
                            for j in range(len(names))) for s in STAGES]
        print(f"| {a} vs {b} | " + " | ".join(cells) + " |")
    print("\nManual against localiser: one rigid offset of each whole stack (rotation deg, shift mm, about the "
          "atlas origin) and the median E.D. with it undone (mm):\n")
    for a, b in (("manual 1", "localiser 1"), ("manual 2", "localiser 2")):
        for stage in list(STAGES)[1:]:
            cells = []
            for j in range(len(names)):
                pa, ka = slice_poses(runs[a][0][stage][j], runs[a][1][j])
                pb, kb = slice_poses(runs[b][0][stage][j], runs[a][1][j])
                frame, left = common_frame(pb[ka & kb], pa[ka & kb], np.zeros(3))
                row = as_row(frame)
                cells.append(f"{np.linalg.norm(row[:3]):.1f} deg {np.linalg.norm(row[3:]):.1f} mm, {np.median(left):.1f}")
            print(f"- {a} vs {b}, {stage}: " + "; ".join(f"{n} {c}" for n, c in zip(names, cells)))
    print("\nThe stack stage per run and stack: the network's per-slice noise it estimated (mm), whether the stack "
          "decided its left-right branch (its margin), slices it flagged inconsistent:\n")
    for key, (_, _, staged) in runs.items():
        print(f"- {key}: " + "; ".join(
            f"{n} noise {p.poses.fit.noise_mm:.1f}, branch {'decided' if p.poses.fit.branch_decided else 'from the request'}"
            f" ({p.poses.fit.branch_margin:.2f}), {int(p.poses.fit.inconsistent.sum())} inconsistent"
            for n, p in zip(names, staged)))
    if args.slices:
        a, b = runs["manual 1"], runs["localiser 1"]
        for j, n in enumerate(names):
            pa, ka = slice_poses(a[0]["network"][j], a[1][j])
            pb, kb = slice_poses(b[0]["network"][j], a[1][j])
            plane = float(getattr(estimator.info, "symmetry_plane_x_mm", twin.DEFAULT_PLANE_X_MM))
            ed, ed_min = anchors.ed(pa, pb), twin.twin_min_ed(pa, pb, plane)      # about the model's plane
            print(f"\n{n}: slice, mask pixels manual / localiser, Dice, centroid shift (mm), network poses' E.D. / twin-min (mm)")
            for k in range(masks[j].shape[2]):
                m, f = masks[j][..., k], found[j][..., k]
                shift = np.linalg.norm((np.argwhere(m).mean(0) - np.argwhere(f).mean(0)) * volumes[j].spacing[:2]) \
                    if m.any() and f.any() else float("nan")
                mark = "" if ka[k] and kb[k] else " (empty in one)"
                print(f"  {k:2d}  {int(m.sum()):5d} / {int(f.sum()):5d}  {dice(f, m):.2f}  {shift:5.1f}  "
                      f"{ed[k]:6.1f} / {ed_min[k]:6.1f}{mark}")


def oracle_masks(found: np.ndarray, manual: np.ndarray, below: float) -> np.ndarray:
    """``found`` with the manual mask on every slice (last axis) whose Dice against it is under ``below``.

    Example:
        >>> m = np.zeros((4, 4, 2), bool); m[1:3, 1:3] = True
        >>> f = m.copy(); f[..., 1] = False
        >>> int(oracle_masks(f, m, 0.8)[..., 1].sum()), int(oracle_masks(f, m, 0.0)[..., 1].sum())
        (4, 0)
    """
    out = found.copy()
    for k in range(found.shape[-1]):
        if dice(found[..., k], manual[..., k]) < below:
            out[..., k] = manual[..., k]
    return out


if __name__ == "__main__":
    main()
