"""Cost of matching the stacks' intensities in the image stage (:mod:`service.consistency.intensity_match`).

Runs the image refinement (:func:`~service.consistency.image_refinement.refine`) on the same
stacks and starting poses with the intensities matched (the service's default) and without, best
of 3 each, timed alternately, and prints both times and their ratio (a ratio holds on a loaded
machine too). The
stacks: a phantom acquisition of three stacks (64 x 64, mild motion) and, where ``../shared/data``
holds it, the shared real scan's three stacks with their manual masks at the poses ``/v1/predict``'s
stack stage gives them. Run: ``.venv/bin/python benchmarks/image_stage_bench.py``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import service.consistency.image_refinement as image_refinement  # noqa: E402
from benchmarks.timing import alternated  # noqa: E402
from service.core.machine import cpu_description  # noqa: E402
from tests.consistency.conftest import disturbed, prepared_acquisition  # noqa: E402

REAL_SCAN = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_scans" / "mial_lausanne_t30"


def refined_with(matched_from: int | None, stacks: list, poses: list, expected: list) -> None:
    """One refinement with ``MATCHED_FROM_PASS = matched_from``, the service's setting restored after."""
    saved = image_refinement.MATCHED_FROM_PASS
    image_refinement.MATCHED_FROM_PASS = matched_from
    try:
        image_refinement.refine(stacks, poses, expected)
    finally:
        image_refinement.MATCHED_FROM_PASS = saved


def timed(stacks: list, poses: list, expected: list, repeats: int = 3) -> dict[str, float]:
    """Best-of-``repeats`` seconds of one refinement unmatched (``plain``) and matched (``matched``, the
    service's setting), timed alternately (:func:`~benchmarks.timing.alternated`)."""
    matched = image_refinement.MATCHED_FROM_PASS
    return alternated({"plain": lambda: refined_with(None, stacks, poses, expected),
                       "matched": lambda: refined_with(matched, stacks, poses, expected)}, repeats)


def real_scan_case() -> tuple[list, list, list] | None:
    """The shared real scan's stacks (manual masks) at the stack stage's poses, or None without the data."""
    if not REAL_SCAN.exists():
        return None
    from model_export.localiser.evaluate import masked_files
    from model_export.localiser.pose_accuracy import pose_estimator
    from service.io.volume import read_volume
    from service.pipeline import image_stage, predict as pipeline
    from service.pipeline.prepare import StackUpload, prepare_stacks

    estimator = pose_estimator()
    uploads = [StackUpload(name, read_volume(stack), read_volume(mask)) for name, stack, mask in masked_files(REAL_SCAN)]
    prepared = prepare_stacks(uploads, estimator.info, True, workers=2)
    predictions, _ = pipeline.predict(prepared, estimator, 100, estimator.info.variance_threshold, image_consistency=False)
    stacks = [image_stage.stack_images(p) for p in prepared]
    return stacks, [p.poses.poses for p in predictions], [p.poses.expected_error_mm for p in predictions]


def main() -> None:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    print(f"machine: {cpu_description()}")
    images, truth = prepared_acquisition()
    cases = {"phantom, 3 stacks of 64 x 64": (images, disturbed(truth, 2.0, 2.0, seed=4),
                                              [np.full(len(t), 4.0) for t in truth])}
    real = real_scan_case()
    if real is not None:
        cases["shared real scan, 3 stacks of 320 x 320, manual masks"] = real
    for name, (stacks, poses, expected) in cases.items():
        times = timed(stacks, poses, expected)
        plain, matched = times["plain"], times["matched"]
        print(f"{name}: image stage {1000 * plain:.0f} ms unmatched, {1000 * matched:.0f} ms matched "
              f"(x{matched / plain:.2f})")


if __name__ == "__main__":
    main()
