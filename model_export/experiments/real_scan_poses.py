"""A real scan's poses without masks against those with its manual masks, split into the common
rigid move of the whole answer (the atlas frame the request settles in) and what is left per stack.

Real scans have no true poses; two answers for the same stacks can still be compared. A scan folder
holds ``NAME.nii.gz`` beside ``NAME_brain_mask.nii.gz`` (the manual mask, sent with
``masks_hold_csf``). Both answers go through ``/v1/predict``'s pipeline (every stage, MC 100) with
the same MC draws (a model with fixed draws), so only the masks separate them. Printed
per stack: the median E.D. between the two answers over the slices both pose, the accepted slices of
each, the localiser's confidence, then per-slice distances (``M``: posed with the manual mask only,
``L``: with the localiser's only, ``*``: accepted without masks); then the common rigid offset (the
Fréchet mean of the two answers' differences about the brain's centre,
:func:`~model_export.experiments.frame_bias.common_frame`) over the slices both answers accept, and
the median E.D. per stack once it is undone, over those slices (the poses a user would take from
either answer).

``--floor`` measures what the comparison rests on: the answers of each mask mode against each other
under other MC draws (the model's seed + 0, 1, ...; ``--repeats`` answers a mode, at least 2), the same masks
throughout, so that only the draws separate them. ``--mc-samples`` sets the passes per slice.

    .venv/bin/python model_export/experiments/real_scan_poses.py [SCAN_FOLDER] [--localiser M] [--model M]
        [--stacks A,B] [--no-image-consistency] [--repeats N] [--floor] [--mc-samples 100]
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.experiments.frame_bias import common_frame  # noqa: E402
from model_export.localiser.evaluate import REAL_SCANS, masked_files  # noqa: E402
from model_export.localiser.pose_accuracy import pose_estimator  # noqa: E402
from model_export.localiser.pose_accuracy import slice_poses  # noqa: E402
from service.pipeline.documents import stack_objects  # noqa: E402
from service.geometry import anchors, se3  # noqa: E402
from service.inference.acceptance import ATLAS_CENTRE_MM  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator, PoseEstimator  # noqa: E402
from service.io.volume import Volume, read_volume  # noqa: E402
from service.pipeline.predict import predict  # noqa: E402
from service.pipeline.prepare import StackUpload, prepare_stacks  # noqa: E402
from service.preprocess.localise import Localiser, default_localiser  # noqa: E402


def answer(volumes: dict[str, Volume], manual: dict[str, Volume] | None, localiser: Localiser,
           estimator: PoseEstimator, image_consistency: bool = True, mc_samples: int = 100) -> tuple[list[dict], list]:
    """``/v1/predict``'s answer (its ``stacks`` objects) and the prepared stacks for the named
    ``volumes``: with their ``manual`` masks (sent with ``masks_hold_csf``), or without masks."""
    names = list(volumes)
    uploads = [StackUpload(n, volumes[n], manual[n] if manual else None, f"{n}_brain_mask" if manual else None,
                           mask_holds_csf=bool(manual)) for n in names]
    prepared = prepare_stacks(uploads, estimator.info, True, workers=2, localiser=localiser)
    predictions, _ = predict(prepared, estimator, mc_samples, estimator.info.variance_threshold,
                             image_consistency=image_consistency)
    return stack_objects(predictions), prepared


def read_scan(scan: Path, stacks: str | None = None) -> tuple[dict[str, Volume], dict[str, Volume]]:
    """The stacks of a real ``scan`` folder that have manual masks (or those of ``stacks``, comma-
    separated names), and their masks, by name."""
    files = {n: (stack, mask) for n, stack, mask in masked_files(scan)}
    names = stacks.split(",") if stacks else list(files)
    return {n: read_volume(files[n][0]) for n in names}, {n: read_volume(files[n][1]) for n in names}


def compare(volumes: dict[str, Volume], manual: dict[str, Volume], localiser: Localiser,
            estimator: PoseEstimator, image_consistency: bool = True, mc_samples: int = 100) -> dict[str, float] | None:
    """One answer with the manual masks and one without, printed per stack and as a whole; returns
    the whole's figures (None when no slice is accepted in both)."""
    (with_masks, prepared), (without, _) = [answer(volumes, m, localiser, estimator, image_consistency, mc_samples)
                                            for m in (manual, None)]
    return apart(list(volumes), with_masks, without, prepared, ("with masks", "without"))


def apart(names: list[str], first: list[dict], second: list[dict], prepared: list,
          labels: tuple[str, str]) -> dict[str, float] | None:
    """Two answers for the same stacks (``stacks`` objects, the ``prepared`` stacks of the first),
    printed per stack (``M``: posed in the first only, ``L``: in the second only, ``*``: accepted in
    the second) and as a whole: the second's common rigid offset from the first over the slices both
    accept, and what is left once it is undone; returns the whole's figures (None when no slice is
    accepted in both)."""
    pairs = []
    for name, sa, sb, p in zip(names, first, second, prepared):
        (xa, ka), (xb, kb) = slice_poses(sa, p), slice_poses(sb, p)
        d = anchors.ed(xa, xb)
        both = ka & kb
        usable = both & np.array([x["accepted"] and y["accepted"] for x, y in zip(sa["slices"], sb["slices"])])
        pairs.append((xa[usable], xb[usable]))
        accepted = [sum(s["accepted"] for s in st["slices"]) for st in (sa, sb)]
        marks = [f"{k}:" + ("-" if not (ka[k] or kb[k]) else "M" if not kb[k] else "L" if not ka[k] else f"{d[k]:.0f}")
                 + ("*" if sb["slices"][k]["accepted"] else "") for k in range(len(d))]
        print(f"{name}: median {np.median(d[both]):.1f} mm over {both.sum()} slices; accepted {labels[0]} "
              f"{accepted[0]}, {labels[1]} {accepted[1]}; localiser confidence {sb['localisation']['confidence']:.2f}")
        print("   " + " ".join(marks))
    a, b = np.concatenate([x for x, _ in pairs]), np.concatenate([y for _, y in pairs])
    if not len(a):
        print("no slice is accepted in both answers")
        return None
    frame, left = common_frame(b, a, ATLAS_CENTRE_MM)                # the second answer against the first
    angle = np.degrees(np.linalg.norm(se3.so3_log(frame[:3, :3])))
    per_stack = np.split(left, np.cumsum([len(x) for x, _ in pairs])[:-1])
    out = {"slices": len(a), "median_ed_mm": float(np.median(anchors.ed(a, b))), "offset_mm": float(np.linalg.norm(frame[:3, 3])),
           "offset_deg": float(angle), "undone_mm": float(np.median(left)), "stacks_in": sum(len(d) > 0 for d in per_stack)}
    print(f"slices both answers accept: {len(a)}; between them median {out['median_ed_mm']:.2f} mm; "
          f"common offset {out['offset_mm']:.2f} mm / {angle:.2f} deg about the brain's centre; "
          f"median E.D. once undone {out['undone_mm']:.2f} mm (per stack "
          + ", ".join(f"{np.median(d):.2f}" if len(d) else "-" for d in per_stack) + ")")
    return out


def floor(volumes: dict[str, Volume], manual: dict[str, Volume], localiser: Localiser,
          estimators: list[PoseEstimator], image_consistency: bool = True, mc_samples: int = 100,
          ) -> dict[str, list[dict[str, float]]]:
    """Per mask mode (the manual masks, none), every pair of answers under the draws of
    ``estimators`` (the same masks and model, other MC draws): :func:`apart`'s figures per pair."""
    out: dict[str, list[dict[str, float]]] = {}
    for mode, masks in (("manual masks", manual), ("no masks", None)):
        runs = [answer(volumes, masks, localiser, e, image_consistency, mc_samples) for e in estimators]
        out[mode] = []
        for i, j in itertools.combinations(range(len(runs)), 2):
            print(f"-- {mode}: draws {i} against draws {j}")
            figures = apart(list(volumes), runs[i][0], runs[j][0], runs[i][1], (f"draws {i}", f"draws {j}"))
            if figures:
                out[mode].append(figures)
    return out


def summary(runs: list[dict[str, float]]) -> str:
    """The median and range of each figure over ``runs``."""
    return "; ".join(f"{k} {np.median([r[k] for r in runs]):.2f} ({min(r[k] for r in runs):.2f}-{max(r[k] for r in runs):.2f})"
                     for k in runs[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scan", type=Path, nargs="?", default=REAL_SCANS / "mial_lausanne_t30")
    ap.add_argument("--localiser", type=Path, help="a localiser ONNX file (default: the shipped one)")
    ap.add_argument("--model", type=Path, help="the pose model (default: the shipped one)")
    ap.add_argument("--stacks", help="comma-separated names: these stacks alone (default: every masked one)")
    ap.add_argument("--no-image-consistency", action="store_true", help="both answers without the image stage")
    ap.add_argument("--mc-samples", type=int, default=100, help="MC passes per slice")
    ap.add_argument("--floor", action="store_true",
                    help="each mask mode's answers against each other under other MC draws instead")
    ap.add_argument("--repeats", type=int, default=1,
                    help="pairs of answers, each pair with the draws of the model's seed + 0, 1, ...; then their range")
    args = ap.parse_args()
    if args.floor and args.repeats < 2:
        ap.error("--floor compares answers under other draws: give --repeats 2 or more")
    localiser = Localiser.load(args.localiser) if args.localiser else default_localiser()
    estimator = pose_estimator(args.model)
    volumes, manual = read_scan(args.scan, args.stacks)
    seeded = [estimator if r == 0 or estimator.model.mc_seed is None
              else OnnxPoseEstimator(estimator.model.with_seed(estimator.model.mc_seed + r)) for r in range(args.repeats)]
    if args.floor:
        for mode, pairs in floor(volumes, manual, localiser, seeded, not args.no_image_consistency, args.mc_samples).items():
            if pairs:
                print(f"{mode}, over {len(pairs)} pairs of draws: {summary(pairs)}")
        return
    runs = [compare(volumes, manual, localiser, e, not args.no_image_consistency, args.mc_samples) for e in seeded]
    runs = [r for r in runs if r]
    if len(runs) > 1:
        print(f"over {len(runs)} pairs: {summary(runs)}")


if __name__ == "__main__":
    main()
