"""How much a pose network's single-slice answer depends on the mask's exact outline.

A learned localiser's mask differs from the manual one by a few pixels all round and, on some slices,
by a missing or an extra piece (a lobe lying in textured tissue, the eyes below the frontal lobes).
This script cuts the same simulated slices of the validation volumes (3 mm, 1.1 mm pixels, moderate
noise; with ``--surroundings``, a head's CSF, skull, scalp and tissue outside the brain instead of the
skull-stripped atlas's black, :func:`~model_export.simulate.dress`, so that a mask larger than the brain
shows what it would in a scan) and feeds the network each slice with its true mask and with edited masks: dilated or eroded
by 2 px, a disc of 8 px bitten out of or added at a random point of the outline, and the training
simulation's smooth boundary wobble (``mask_wobble_px`` up to 6 px, :func:`~model_export.simulate.wobble_masks`).
For each model and variant it prints the E.D. against the truth and twin-min (the nearer of the
truth and its left-right twin; median and mean), the share of twin-min errors over 10 mm and the
per-slice change of the twin-min error from the true mask's (median absolute).

    .venv/bin/python model_export/experiments/mask_sensitivity.py service/models/default/model.onnx [B.onnx ...]
        [--per-volume 40] [--mc 20] [--surroundings]
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
from model_export.simulate import SimulationConfig, SliceSimulator, wobble_masks  # noqa: E402
from model_export.train import pose_errors  # noqa: E402
from service.geometry import sampling  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator, statistics  # noqa: E402
from service.inference.model_file import load_model  # noqa: E402
from service.preprocess.slices import preprocess_slices  # noqa: E402

PIXEL_MM = 1.1
THICKNESS_MM = 3.0


def _disc(radius: int) -> NDArray[np.bool_]:
    yy, xx = np.ogrid[-radius:radius + 1, -radius:radius + 1]
    return (yy ** 2 + xx ** 2 <= radius ** 2)[None]


def edit_outline(masks: NDArray[np.bool_], radius: int, add: bool, rng: np.random.Generator) -> NDArray[np.bool_]:
    """Each mask with a disc of ``radius`` px added at (``add``) or bitten out of a random outline
    point, holes filled.

    Example:
        >>> m = np.zeros((1, 40, 40), bool); m[0, 10:30, 10:30] = True
        >>> int(edit_outline(m, 4, False, np.random.default_rng(0)).sum()) < int(m.sum())
        True
    """
    out = masks.copy()
    yy, xx = np.ogrid[:masks.shape[1], :masks.shape[2]]
    for k, m in enumerate(masks):
        edge = np.argwhere(m & ~ndimage.binary_erosion(m))
        if not len(edge):
            continue
        cy, cx = edge[rng.integers(len(edge))]
        disc = (yy - cy) ** 2 + (xx - cx) ** 2 <= radius ** 2
        out[k] = ndimage.binary_fill_holes(m | disc if add else m & ~disc)
    return out


def variants(masks: NDArray[np.bool_], rng: np.random.Generator) -> dict[str, NDArray[np.bool_]]:
    """The edited masks of every variant, in a fixed order (one random stream for all)."""
    wobble = SimulationConfig(mask_wobble_share=1.0, mask_wobble_px=(0.0, 6.0))
    return {"true": masks, "dilated 2 px": ndimage.binary_dilation(masks, _disc(2)),
            "eroded 2 px": ndimage.binary_erosion(masks, _disc(2)),
            "bite 8 px": edit_outline(masks, 8, False, rng), "bulge 8 px": edit_outline(masks, 8, True, rng),
            "wobble <= 6 px": wobble_masks(masks, wobble, rng)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("models", type=Path, nargs="+")
    ap.add_argument("--per-volume", type=int, default=40)
    ap.add_argument("--mc", type=int, default=20)
    ap.add_argument("--root", type=Path, default=DEFAULT_ATLAS_ROOT)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--surroundings", action="store_true", help="a head's surroundings outside the brain")
    args = ap.parse_args()
    _, names = split(args.root)
    volumes = load_volumes(names, args.root)
    models = [load_model(p) for p in args.models]
    info = models[0].info
    config = SimulationConfig.validation(size=info.input_size, pixel_mm=info.pixel_spacing_mm,
                                         surroundings_share=1.0 if args.surroundings else 0.0)
    simulator = SliceSimulator(volumes, config)
    rng = np.random.default_rng(args.seed)
    estimators = {path: OnnxPoseEstimator(model) for path, model in zip(args.models, models)}
    errors: dict[Path, dict[str, list[dict[str, NDArray]]]] = {path: {} for path in args.models}
    for index, volume in enumerate(volumes):
        poses = simulator.sample_poses(volume, args.per_volume, rng)
        images, masks = simulator.acquire(index, poses, PIXEL_MM, THICKNESS_MM, 1.0)
        distance = simulator.distance(index, poses, PIXEL_MM) if args.surroundings else None
        images, _ = simulator.corrupt(images, masks, rng, distance)
        for name, edited in variants(masks > 0.5, rng).items():
            prep = preprocess_slices(images, edited, (PIXEL_MM, PIXEL_MM), info.input_size, info.pixel_spacing_mm)
            truth = sampling.recentre(poses, prep.centroid_mm)
            for path, estimator in estimators.items():
                plane = estimator.info.symmetry_plane_x_mm
                mean = statistics(estimator.sample_labels(prep.inputs, args.mc), estimator.info.label_type, plane).mean
                errors[path].setdefault(name, []).append(pose_errors(mean, truth, plane))
    print(f"{len(volumes)} validation volumes x {args.per_volume} slices, MC {args.mc}, "
          f"{'surroundings' if args.surroundings else 'black'} outside the brain; E.D. (mm)")
    print("| model | mask | median (truth / twin-min) | mean (truth / twin-min) | twin-min > 10 mm | median change of twin-min |")
    print("|---|---|---|---|---|---|")
    for path, by_mask in errors.items():
        ed = {name: np.concatenate([p["ed_mm"] for p in parts]) for name, parts in by_mask.items()}
        twin_min = {name: np.concatenate([p["ed_twin_mm"] for p in parts]) for name, parts in by_mask.items()}
        for name, e in twin_min.items():
            print(f"| {path} | {name} | {np.median(ed[name]):.2f} / {np.median(e):.2f} | {ed[name].mean():.2f} / "
                  f"{e.mean():.2f} | {np.mean(e > 10):.2f} | {np.median(np.abs(e - twin_min['true'])):.2f} |")

if __name__ == "__main__":
    main()
