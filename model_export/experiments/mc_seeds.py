"""What the seed of a model's fixed MC-dropout draws changes, on single validation slices.

A model with fixed draws (``mc_seed``; docs/training.md, "Export and MC dropout") answers every
request with one ensemble of dropout sub-networks. Per seed of ``--seeds`` (the model's session
reused, :meth:`~service.inference.model_file.LoadedModel.with_seed`), on ``--per-volume`` simulated
slices of each validation volume: the twin-min mean and median E.D. of the MC-100 means (every
test-time view), and the common rigid offset of those poses, each on the truth's branch
(:func:`~service.geometry.twin.nearer`), from the truth about the atlas centre
(:func:`~model_export.experiments.frame_bias.common_frame`): a bias the ensemble would put on every
slice. Then each seed's offset against the first seed's.

    .venv/bin/python model_export/experiments/mc_seeds.py [--seeds 0,1,2,3,4] [--per-volume 60]   # needs the atlases
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.atlas import DEFAULT_ATLAS_ROOT, split  # noqa: E402
from model_export.evaluate import pose_errors, validation_set  # noqa: E402
from model_export.experiments.frame_bias import common_frame  # noqa: E402
from model_export.simulate import SimulationConfig  # noqa: E402
from service.core.settings import DEFAULT_MODELS_DIR  # noqa: E402
from service.geometry import se3, twin  # noqa: E402
from service.inference.acceptance import ATLAS_CENTRE_MM  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator  # noqa: E402
from service.inference.model_file import load_model  # noqa: E402


def offset_text(frame: np.ndarray) -> str:
    """A rigid offset as its angle and shift."""
    return f"{np.degrees(np.linalg.norm(se3.so3_log(frame[:3, :3]))):.2f} deg, {np.linalg.norm(frame[:3, 3]):.2f} mm"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=DEFAULT_MODELS_DIR / "default" / "model.onnx")
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--per-volume", type=int, default=60)
    ap.add_argument("--root", type=Path, default=DEFAULT_ATLAS_ROOT)
    args = ap.parse_args()
    model = load_model(args.model)
    if model.mc_seed is None:
        sys.exit(f"{args.model} draws in its graph: `svrnet-train fix-draws` it first")
    info, plane = model.info, model.info.symmetry_plane_x_mm
    config = SimulationConfig.validation(size=info.input_size, pixel_mm=info.pixel_spacing_mm)
    val = validation_set(split(args.root)[1], args.root, args.per_volume, seed=12345, config=config)
    frames = []
    for seed in (int(s) for s in args.seeds.split(",")):
        mean = OnnxPoseEstimator(model.with_seed(seed)).estimate(val.inputs, 100).mean
        err = pose_errors(mean, val.poses, plane)
        # Each pose on the truth's branch (the pose or its twin, whichever is nearer the truth): a
        # truth mirrored instead would turn a slice's offset into its mirror image.
        frame, _ = common_frame(twin.nearer(val.poses, mean, plane), val.poses, ATLAS_CENTRE_MM)
        frames.append(frame)
        print(f"seed {seed}: twin-min E.D. mean {err['ed_twin_mm'].mean():.2f} mm, median "
              f"{np.median(err['ed_twin_mm']):.2f} mm; common offset from the truth {offset_text(frame)}; "
              f"against the first seed's {offset_text(frame @ se3.inverse(frames[0]))}", flush=True)


if __name__ == "__main__":
    main()
