"""Where whole-uterus requests lose their accuracy after the stages: the request's common offset or
the slices' placement relative to each other, and what the stacks' intensities have to do with it.

Requests of three stacks at mild motion (the validation brains, seed 2,000,000, the atlas's own brain
mask; :func:`~model_export.localiser.pose_accuracy.validation_cases`, ``--planning orthogonal``) go
through ``/v1/predict``'s pipeline. Per request it prints the RMS E.D. of the slices with brain, the
RMS of the request's common rigid offset (:func:`~model_export.experiments.frame_bias.common_frame`,
about the slices' centre) and of what is left once it is undone (each slice's own placement: what the
image stage works on), and the image stage's term per weighted point at the true poses and where
the stage ended (in units of its noise).

* ``scenes``: generated whole-uterus stacks; ``--without bias,gains`` draws them without the
  generator's bias fields or slice-to-slice gains (the other draws the same);
* ``scenes-atlas-image``: the same stacks, each slice's image the atlas sampled at its true pose;
* ``acquisitions``: the pose benchmarks' stacks (:func:`~model_export.acquisitions.simulate_acquisition`).

``--unmatched`` turns off the image stage's intensity matching
(:data:`~service.consistency.image_refinement.MATCHED_FROM_PASS`). Needs ``../shared/data``.

    .venv/bin/python model_export/experiments/scene_intensities.py scenes [--without bias,gains] [--unmatched] [--requests 5]
    .venv/bin/python model_export/experiments/scene_intensities.py acquisitions [--requests 8]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import service.consistency.image_refinement as image_refinement  # noqa: E402
from model_export.experiments.frame_bias import common_frame  # noqa: E402
from model_export.experiments.scene_difficulty import requests_of  # noqa: E402
from model_export.localiser import pose_accuracy, scenes  # noqa: E402
from model_export.localiser.pose_accuracy import pose_estimator  # noqa: E402
from service.geometry import anchors  # noqa: E402
from service.geometry.pose import about_centre  # noqa: E402
from service.pipeline import image_stage, predict as pipeline  # noqa: E402
from service.pipeline.prepare import prepare_stacks  # noqa: E402

NUISANCES = ("bias", "gains")


def own_frame(poses: NDArray, truth: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``[n]`` twice: each pose's E.D. once the request's common error about the slices' centre
    (:func:`~model_export.experiments.frame_bias.common_frame`) is undone, and that error's E.D. at
    each true pose.

    Example (every pose moved alike by 2 mm: all of it is the common error):
        >>> truth = np.repeat(np.eye(4)[None], 3, 0); truth[:, 2, 3] = [-3.0, 0.0, 3.0]
        >>> moved = truth.copy(); moved[:, 0, 3] += 2.0
        >>> [e.round(6).tolist() for e in own_frame(moved, truth)]
        [[0.0, 0.0, 0.0], [2.0, 2.0, 2.0]]
    """
    centre = truth[:, :3, 3].mean(axis=0)
    frame, own = common_frame(poses, truth, centre)
    return own, anchors.ed(about_centre(frame, centre)[None] @ truth, truth)


def without(nuisances: list[str]) -> None:
    """The scene generator with ``nuisances`` (:data:`NUISANCES`) left out, its draws made all the same."""
    for name, function in (("bias", "bias_field"), ("gains", "slice_gains")):
        if name in nuisances:
            drawn = getattr(scenes, function)
            setattr(scenes, function, lambda *a, drawn=drawn: (drawn(*a), 1.0)[1])


def request_row(case: list, estimator) -> dict[str, float]:  # noqa: ANN001
    """One request's figures (see the module docstring)."""
    info = estimator.info
    prepared = prepare_stacks([pose_accuracy._upload(s, "brain") for s in case], info, True, workers=1)
    truth = [p.in_network_frame(s.atlas_from_voxel) for p, s in zip(prepared, case)]
    predictions, _ = pipeline.predict(prepared, estimator, 100, info.variance_threshold)
    keep = [s.brain.sum(axis=(0, 1)) >= pose_accuracy.MIN_BRAIN_PIXELS for s in case]
    poses = np.concatenate([p.poses.poses[k] for p, k in zip(predictions, keep)])
    true = np.concatenate([t[k] for t, k in zip(truth, keep)])
    own, common = own_frame(poses, true)
    active = [np.isfinite(p.estimate.spread_mm) for p in predictions]
    images = [image_stage.stack_images(p, a) for p, a in zip(prepared, active)]
    at_truth = image_refinement.refine(images, truth, [np.full(len(t), 3.0) for t in truth], iterations=0).cost_after
    after = predictions[0].poses.image_consistency
    rms = lambda e: float(np.sqrt(np.mean(e ** 2)))  # noqa: E731
    return {"ed": rms(anchors.ed(poses, true)), "own": rms(own), "common": rms(common), "at_truth": at_truth,
            "after": float("nan") if after is None else after.mismatch_after}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("source", choices=("scenes", "scenes-atlas-image", "acquisitions"))
    ap.add_argument("--requests", type=int, default=5)
    ap.add_argument("--planning", default="orthogonal", choices=pose_accuracy.PLANNINGS)
    ap.add_argument("--without", default="", help=f"scene nuisances left out, comma-separated: {', '.join(NUISANCES)}")
    ap.add_argument("--unmatched", action="store_true", help="the image stage without intensity matching")
    args = ap.parse_args()
    left_out = [n for n in args.without.split(",") if n]
    if any(n not in NUISANCES for n in left_out) or (left_out and args.source == "acquisitions"):
        ap.error(f"--without takes {', '.join(NUISANCES)}, for the scenes")
    without(left_out)
    if args.unmatched:
        image_refinement.MATCHED_FROM_PASS = None
    cases = requests_of(args.source, args.requests, args.planning)
    estimator = pose_estimator()
    rows = []
    for i, case in enumerate(cases):
        rows.append(request_row(case, estimator))
        r = rows[-1]
        print(f"request {i}: RMS E.D. {r['ed']:.2f}, own frame {r['own']:.2f}, common offset {r['common']:.2f} mm; "
              f"image term at the truth {r['at_truth']:.2f}, after the stage {r['after']:.2f}", flush=True)
    mean = {k: float(np.sqrt(np.mean([r[k] ** 2 for r in rows]))) for k in ("ed", "own", "common")}
    print(f"{args.source}: RMS over the requests: E.D. {mean['ed']:.2f}, own frame {mean['own']:.2f}, common offset "
          f"{mean['common']:.2f} mm; image term at the truth {np.mean([r['at_truth'] for r in rows]):.2f}, after "
          f"{np.nanmean([r['after'] for r in rows]):.2f} (means)")


if __name__ == "__main__":
    main()
