"""Test-time views 8, 4 and 1 through the whole pipeline: inference time per slice and the final
E.D. (truth and twin-min) on the same simulated acquisitions of the validation volumes, the model's
calibration as it is (not re-fitted per view count).

    .venv/bin/python model_export/experiments/views_latency.py moderate,mild 2
"""

import sys
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from model_export.atlas import load_volumes, split, DEFAULT_ATLAS_ROOT  # noqa: E402
from model_export.acquisitions import simulate_acquisition  # noqa: E402
from model_export.evaluate_acquisitions import prepare_acquisition, score, Scored, summarise  # noqa: E402
from service.pipeline.predict import predict  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator  # noqa: E402
from service.inference.model_file import load_model  # noqa: E402


def main(levels: str, per_volume: int) -> None:
    """Print, per motion level and view count, the final E.D. and the inference time per slice."""
    model = load_model(ROOT / "service" / "models" / "default" / "model.onnx")
    ests = {v: OnnxPoseEstimator(model) for v in (8, 4, 1)}
    for v, e in ests.items():
        e.info = replace(e.info, tta_views=v)
    vols = load_volumes(split(DEFAULT_ATLAS_ROOT)[1], DEFAULT_ATLAS_ROOT)
    rng = np.random.default_rng(31)
    for level in levels.split(","):
        sc = {v: Scored() for v in ests}
        tm = {v: 0.0 for v in ests}
        n = 0
        for vol in vols:
            for _ in range(per_volume):
                stacks = simulate_acquisition(vol.image, vol.mask, vol.affine, rng, level)
                prepared, truth = prepare_acquisition(stacks, model.info)
                n += sum(len(p.prepared.inputs) for p in prepared)
                for v, e in ests.items():
                    preds, t = predict(prepared, e, 100, e.info.variance_threshold)
                    tm[v] += t["inference"]
                    score(preds, prepared, truth, stacks, e.info.symmetry_plane_x_mm, sc[v])
        for v in ests:
            s = summarise(sc[v])
            print(f"{level:9s} views {v}: ED {s['ed']['mean']:.3f} twin-min {s['ed_min']['mean']:.3f} median {s['ed']['median']:.3f} | inference {1000 * tm[v] / n:.2f} ms/slice")
        sys.stdout.flush()


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]))
