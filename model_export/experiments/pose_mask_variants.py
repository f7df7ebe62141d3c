"""The pose network's mask from the localiser, cut and inset otherwise: poses against the truth on
generated whole-uterus scenes, and a real scan's poses without masks against those with its manual
masks.

The localiser's pose mask is its probabilities cut at ``THRESHOLD`` less their outer
``POSE_MASK_INSET_MM`` (:mod:`service.preprocess.localise`; the inset applies to uploads sent with
``masks_hold_csf`` too). Each variant sets both and measures, with the model's fixed draws (the
variants see the same samples):

* :func:`~model_export.localiser.pose_accuracy.pose_accuracy` on ``--scenes`` generated scenes
  (the localiser's masks only): median / mean E.D. against the truth, and the twin-min mean;
* :func:`~model_export.experiments.real_scan_poses.compare` on the shared real scan, one pair of
  answers per seed of ``--seeds``: median E.D. between them and their common turn.

    .venv/bin/python model_export/experiments/pose_mask_variants.py [--scenes 10] [--seeds 0,1] \\
        [--variants 0.5/2,0.4/2,0.6/2,0.5/1,0.5/3,0.4/3]                # needs ../shared/data
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import service.preprocess.localise as localise  # noqa: E402
from model_export.experiments.real_scan_poses import compare, read_scan  # noqa: E402
from model_export.localiser.evaluate import REAL_SCANS, _pose_estimator  # noqa: E402
from model_export.localiser.pose_accuracy import pose_accuracy, validation_scenes  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=10)
    ap.add_argument("--seeds", default="0,1", help="the draws of each real-scan pair")
    ap.add_argument("--variants", default="0.5/2,0.4/2,0.6/2,0.5/1,0.5/3,0.4/3", help="CUT/INSET_MM, comma-separated")
    args = ap.parse_args()
    estimator, localiser = _pose_estimator(), localise.default_localiser()
    scenes = validation_scenes(args.scenes)
    volumes, manual = read_scan(REAL_SCANS / "mial_lausanne_t30")
    for variant in args.variants.split(","):
        cut, inset = (float(x) for x in variant.split("/"))
        localise.THRESHOLD, localise.POSE_MASK_INSET_MM = cut, inset
        acc = pose_accuracy(scenes, estimator, localiser, ("localiser",))["localiser"]
        pairs = []
        for seed in (int(s) for s in args.seeds.split(",")):
            with contextlib.redirect_stdout(io.StringIO()):        # compare() prints per stack
                pairs.append(compare(volumes, manual, localiser, OnnxPoseEstimator(estimator.model.with_seed(seed))))
        real = "; ".join(f"{p['median_ed_mm']:.2f} mm, turn {p['offset_deg']:.1f} deg" if p else "none accepted in both"
                         for p in pairs)
        print(f"{variant}: scenes {acc['median_ed_mm']:.2f} / {acc['mean_ed_mm']:.2f} mm, twin-min mean "
              f"{acc['mean_twin_min_mm']:.2f} | shared scan without against with masks: {real}", flush=True)


if __name__ == "__main__":
    main()
