"""How far a real request's answer moves when its manual masks change by one pixel: the noise floor
under issue 27's pose gap.

The real scan (``mial_lausanne_t30``, three stacks with manual masks) runs through ``/v1/predict``'s
pipeline (every stage on) with its manual masks, then with every mask changed in the plane of its
slices by one pixel: eroded, dilated, or each pixel of its outline (inside or out) redrawn at random
(``--jitters`` seeds). For each variant it prints the masks' Dice against the manual ones, the
median E.D. of the answer's slice poses from the manual masks' answer, the slices accepted per
stack, and each stack's discrete choices (acquisition order, branch margin and who decided it).
A localiser whose masks lie at Dice 0.97 from the manual ones cannot bring the answers nearer than
this.

    .venv/bin/python model_export/experiments/mask_jitter.py [--jitters 4] [--scan DIR]   # needs ../shared/data/real_scans
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.localiser.evaluate import REAL_SCANS, dice, masked_files, median_ed  # noqa: E402
from model_export.localiser.pose_accuracy import pose_estimator  # noqa: E402
from service.io.volume import Volume, read_volume  # noqa: E402
from service.pipeline.documents import stack_objects  # noqa: E402
from service.pipeline.predict import predict  # noqa: E402
from service.pipeline.prepare import StackUpload, prepare_stacks  # noqa: E402
from service.preprocess.stack import slice_axis_of  # noqa: E402


def changed(mask: NDArray, axis: int, how: str, rng: np.random.Generator) -> NDArray[np.bool_]:
    """``mask`` eroded (``erode``) or dilated (``dilate``) by one pixel in the plane of the slices along
    ``axis``, or with each pixel of its one-pixel outline band drawn inside at random (``jitter``)."""
    cross = np.expand_dims(ndimage.generate_binary_structure(2, 1), axis)
    inside = np.asarray(mask) > 0
    if how == "erode":
        return ndimage.binary_erosion(inside, cross)
    if how == "dilate":
        return ndimage.binary_dilation(inside, cross)
    band = ndimage.binary_dilation(inside, cross) & ~ndimage.binary_erosion(inside, cross)
    return np.where(band, rng.random(inside.shape) < 0.5, inside)


def choices(stack: dict) -> str:
    """A stack answer's discrete choices: acquisition order, branch margin and who set the branch."""
    c = stack["consistency"] or {}
    who = "own" if c.get("branch_decided") else "request" if c.get("branch_from_request") else "none"
    return f"{c.get('acquisition_order', '-')}, margin {c.get('branch_margin') or float('nan'):.2f} ({who})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scan", type=Path, default=REAL_SCANS / "mial_lausanne_t30")
    ap.add_argument("--jitters", type=int, default=4, help="seeds of the random outline")
    ap.add_argument("--model", type=Path, help="the pose model (default: the shipped one)")
    args = ap.parse_args()
    files = masked_files(args.scan)
    if not files:
        sys.exit(f"needs stacks with manual masks in {args.scan}")
    estimator = pose_estimator(args.model)
    stacks = [(name, read_volume(s), read_volume(m)) for name, s, m in files]

    def answer(masks: list[NDArray]) -> tuple[list[dict], list]:
        uploads = [StackUpload(name, volume, Volume(mask.astype(np.uint8), m.affine))
                   for (name, volume, m), mask in zip(stacks, masks)]
        prepared = prepare_stacks(uploads, estimator.info, True, workers=2)
        return stack_objects(predict(prepared, estimator, 100, estimator.info.variance_threshold)[0]), prepared

    manual = [m.array > 0 for _, _, m in stacks]
    axes = [slice_axis_of(np.asarray(v.spacing)) for _, v, _ in stacks]
    base = answer(manual)
    print("manual masks: accepted", [sum(s["accepted"] for s in st["slices"]) for st in base[0]],
          "|", "; ".join(choices(st) for st in base[0]))
    variants = ["erode", "dilate"] + [f"jitter {k}" for k in range(args.jitters)]
    for how in variants:
        rng = np.random.default_rng(int(how.split()[-1]) if how.startswith("jitter") else 0)
        masks = [changed(m, a, how.split()[0], rng) for m, a in zip(manual, axes)]
        got = answer(masks)
        print(f"{how}: Dice {' / '.join(f'{dice(a, b):.3f}' for a, b in zip(masks, manual))}; "
              f"from the manual masks' answer {median_ed(base[0], got[0], base[1])[0]:.2f} mm; accepted "
              f"{[sum(s['accepted'] for s in st['slices']) for st in got[0]]} | "
              + "; ".join(choices(st) for st in got[0]), flush=True)


if __name__ == "__main__":
    main()
