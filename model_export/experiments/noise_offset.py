"""Where a noisy acquisition's error lies: one turn and shift of the whole request, or each slice's own.

Per simulated 3-stack acquisition of the held-out volumes (``scanner_sweep.py``'s draws: its seed,
its 128 mm field of view, 3 mm slices) at a pixel size and Rician noise level, through the whole
pipeline with the masks: the mean and median E.D. of the returned poses against the truth, the
rigid transform of atlas space that best takes the truth onto them (least squares over the anchor
points of the 80 % best slices: the request's common offset, its rotation vector in degrees and its
shift in mm, atlas RAS), and the E.D. once
that offset is undone (what is each slice's own), with the share of slices accepted.

``--smooth T`` first smooths in-plane each stack whose input noise exceeds 0.09 with a Gaussian
that brings white noise down to input noise ``T`` (an experiment: the network's inputs made as
quiet as the slices it learnt from, at the price of their detail).

    .venv/bin/python model_export/experiments/noise_offset.py --pixel-mm 1.6 --noise 0.15 [--smooth 0.06]   # needs ../shared/data
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes, split  # noqa: E402
from model_export.calibrate_noise import acquire  # noqa: E402
from model_export.evaluate_acquisitions import MIN_MASK_PIXELS, run_acquisition  # noqa: E402
from service.pipeline.documents import stack_objects  # noqa: E402
from service.geometry import se3  # noqa: E402
from service.geometry.anchors import ed, encode  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator  # noqa: E402
from service.inference.model_file import load_model  # noqa: E402
from service.preprocess.noise import input_noise  # noqa: E402

SMOOTH_ONSET = 0.09


def common_offset(final: NDArray, true: NDArray, keep_share: float = 0.8) -> NDArray:
    """The rigid transform ``C`` of atlas space that best takes ``true [n, 4, 4]`` onto ``final`` (the
    anchor points of the ``keep_share`` of slices nearest already, least squares).

    Example (every slice turned 3 deg about z and shifted 2 mm along x):
        >>> c = se3.exp(np.array([0.0, 0.0, np.radians(3.0), 2.0, 0.0, 0.0]))
        >>> true = se3.exp(np.random.default_rng(0).normal(0, [0.3, 0.3, 0.3, 10, 10, 10], (12, 6)))
        >>> bool(np.allclose(common_offset(c @ true, true), c))
        True
    """
    e = ed(final, true)
    near = e <= np.quantile(e, keep_share)
    p, q = encode(true[near]).reshape(-1, 3), encode(final[near]).reshape(-1, 3)
    pc, qc = p.mean(0), q.mean(0)
    u, _, vt = np.linalg.svd((p - pc).T @ (q - qc))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    out = np.eye(4)
    out[:3, :3] = vt.T @ d @ u.T
    out[:3, 3] = qc - out[:3, :3] @ pc
    return out


def smoothing(target: float):  # noqa: ANN201
    """A ``preprocess_slices`` that first smooths slices noisier than :data:`SMOOTH_ONSET` down to ``target``
    (a 2D Gaussian of ``s`` pixels divides white noise by ``2 s sqrt(pi)``)."""
    import service.pipeline.prepare as prepare

    plain = prepare.preprocess_slices

    def smoothed(images, masks, pixel_mm, size, pixel_out_mm):  # noqa: ANN001, ANN202
        level = input_noise(images, masks, pixel_mm, pixel_out_mm)
        if np.isfinite(level) and level > SMOOTH_ONSET:
            s = max(0.5, level / (2.0 * np.sqrt(np.pi) * target))
            images = ndimage.gaussian_filter(np.asarray(images, np.float32), (0.0, s, s))
        return plain(images, masks, pixel_mm, size, pixel_out_mm)

    return smoothed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", type=Path, default=Path("service/models/default/model.onnx"))
    ap.add_argument("--root", type=Path, default=DEFAULT_ATLAS_ROOT)
    ap.add_argument("--level", default="mild")
    ap.add_argument("--pixel-mm", type=float, default=1.0)
    ap.add_argument("--noise", type=float, default=0.03)
    ap.add_argument("--per-volume", type=int, default=2)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--smooth", type=float, help="smooth stacks noisier than 0.09 down to this input noise")
    args = ap.parse_args()
    if args.smooth:
        import service.pipeline.prepare as prepare

        prepare.preprocess_slices = smoothing(args.smooth)
    estimator = OnnxPoseEstimator(load_model(args.model))
    volumes = load_volumes(split(args.root)[1], args.root)
    print("| acquisition | mean / median E.D. | common offset: turn, shift | once undone: mean / median | accepted |\n"
          "|---|---|---|---|---|")
    for a, vol in enumerate(volumes * args.per_volume):
        rng = np.random.default_rng([args.seed, a])
        stacks = acquire(vol, rng, args.level, pixel_mm=args.pixel_mm, noise=args.noise)
        (predictions,), prepared, truth = run_acquisition(stacks, estimator)
        final, true, accepted = [], [], []
        for res, p, t in zip(stack_objects(predictions), prepared, truth):
            keep = p.prepared.mask_pixels >= MIN_MASK_PIXELS
            final.append((np.array([s["atlas_from_voxel"] for s in res["slices"]]) @ np.linalg.inv(p.network_from_voxel()))[keep])
            true.append(t[keep])
            accepted.append(np.array([s["accepted"] for s in res["slices"]])[keep])
        f, t, ok = np.concatenate(final), np.concatenate(true), np.concatenate(accepted)
        c = common_offset(f, t)
        e, left = ed(f, t), ed(f, c @ t)
        twist = se3.log(c)
        turn = ", ".join(f"{x:+.1f}" for x in np.degrees(twist[:3]))
        shift = ", ".join(f"{x:+.1f}" for x in c[:3, 3])
        print(f"| {vol.name} ({a}) | {e.mean():.2f} / {np.median(e):.2f} mm | ({turn}) deg, ({shift}) mm "
              f"| {left.mean():.2f} / {np.median(left):.2f} mm | {ok.mean():.0%} |", flush=True)


if __name__ == "__main__":
    main()
