"""Which stack's localisation moves a request's poses: the real scan with one mask swapped at a time.

The real scan (``mial_lausanne_t30``, three stacks with manual masks) runs through ``/v1/predict``'s
pipeline (every stage on) with the manual masks, then with the localiser's mask in place of the
manual one for one stack at a time, for all three, and for each stack alone in its own request. Each
variant's poses are compared slice by slice with those of the manual masks (median E.D. per stack,
over the slices both pose); two runs with the manual masks give the floor (other MC-dropout draws).
Both masks are treated alike (``masks_hold_csf``: the 2 mm inset on both), so what differs is the
mask's extent alone.

A stack whose own poses agree when it is alone, and whose swap moves the other stacks too, acts
through the request's pooled placement (docs/consistency.md).

    .venv/bin/python model_export/experiments/mask_swap.py [--localiser M]   # needs ../shared/data/real_scans
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.localiser.evaluate import REAL_SCANS, csf_mask_upload, dice, masked_stacks, median_ed  # noqa: E402
from model_export.localiser.pose_accuracy import pose_estimator  # noqa: E402
from service.pipeline.documents import stack_objects  # noqa: E402
from service.core.settings import DEFAULT_LOCALISERS_DIR  # noqa: E402
from service.pipeline.predict import predict  # noqa: E402
from service.pipeline.prepare import StackUpload, prepare_stacks  # noqa: E402
from service.preprocess.localise import Localiser  # noqa: E402


def answer(uploads: list[StackUpload], estimator) -> tuple[list[dict], list]:  # noqa: ANN001
    prepared = prepare_stacks(uploads, estimator.info, True, workers=2)
    return stack_objects(predict(prepared, estimator, 100, estimator.info.variance_threshold)[0]), prepared


def per_stack(a: tuple[list[dict], list], b: tuple[list[dict], list], stacks: int) -> list[float]:
    """Per stack of two answers to the same stacks: the median E.D. over the slices both pose."""
    out = [median_ed([a[0][j]], [b[0][j]], [a[1][j]])[0] for j in range(stacks)]
    return [float("nan") if x is None else x for x in out]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--localiser", type=Path, default=DEFAULT_LOCALISERS_DIR / "default" / "model.onnx")
    ap.add_argument("--model", type=Path, help="the pose model (default: the shipped one)")
    ap.add_argument("--scan", type=Path, default=REAL_SCANS / "mial_lausanne_t30")
    args = ap.parse_args()
    estimator, localiser = pose_estimator(args.model), Localiser.load(args.localiser)
    names, volumes, manual, found = masked_stacks(args.scan, localiser)
    if not names:
        sys.exit(f"needs stacks with manual masks in {args.scan}")
    print(f"localiser {localiser.version}; Dice " + ", ".join(
        f"{n} {dice(f, m):.3f}" for n, f, m in zip(names, found, manual)))

    def uploads(which: str, only: list[int]) -> list[StackUpload]:
        """``which[i]``: ``m`` the manual mask for stack ``i``, ``l`` the localiser's."""
        return [csf_mask_upload(names[i], volumes[i], manual[i] if which[i] == "m" else found[i]) for i in only]

    every = list(range(len(names)))
    reference, again = answer(uploads("m" * len(every), every), estimator), answer(uploads("m" * len(every), every), estimator)
    print("| variant | " + " | ".join(names) + " |\n|---|" + "---|" * len(names))
    print("| manual masks again (the floor) | " + " | ".join(f"{x:.1f}" for x in per_stack(reference, again, len(every))) + " |")
    for i in every:
        which = "".join("l" if j == i else "m" for j in every)
        row = per_stack(reference, answer(uploads(which, every), estimator), len(every))
        print(f"| the localiser's mask for {names[i]} | " + " | ".join(f"{x:.1f}" for x in row) + " |")
    row = per_stack(reference, answer(uploads("l" * len(every), every), estimator), len(every))
    print("| the localiser's masks for all | " + " | ".join(f"{x:.1f}" for x in row) + " |")
    alone = []
    for i in every:
        ref = answer(uploads("m" * len(every), [i]), estimator)
        alone.append((per_stack(ref, answer(uploads("m" * len(every), [i]), estimator), 1)[0],
                      per_stack(ref, answer(uploads("l" * len(every), [i]), estimator), 1)[0]))
    print("| each stack alone: manual again / the localiser's | "
          + " | ".join(f"{a:.1f} / {b:.1f}" for a, b in alone) + " |")


if __name__ == "__main__":
    main()
