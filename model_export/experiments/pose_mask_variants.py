"""The pose network's mask from the localiser, cut and inset otherwise: poses against the truth on
generated whole-uterus scenes, and a real scan's poses without masks against those with its manual
masks.

The localiser's pose mask is its probabilities cut at ``THRESHOLD`` less their outer
``POSE_MASK_INSET_MM`` (:mod:`service.preprocess.localisation`; the inset applies to uploads sent with
``masks_hold_csf`` too). Each variant sets both and measures, with the model's fixed draws (the
variants see the same samples):

* :func:`~model_export.localiser.pose_accuracy.pose_accuracy` on ``--scenes`` generated scenes
  (the localiser's masks only): median / mean E.D. against the truth, and the twin-min mean;
* :func:`~model_export.experiments.real_scan_poses.compare` on the shared real scan, one pair of
  answers per seed of ``--seeds``: median E.D. between them and their common turn.

A variant ``rim:EDGE/DEPTH/HI`` cuts the pose mask from the image instead of at a fixed inset
(:func:`image_rim`): the mask (cut at ``THRESHOLD``, or the manual one) less its outer ``EDGE`` mm
and the CSF-bright or skull-dark pixels joined to that edge within ``DEPTH`` mm of the outside, a
pixel bright where it lies ``HI`` of the way from the brain's median to the mask's 98th percentile:
an outline where the brain's surface is, whatever the mask it starts from.

    .venv/bin/python model_export/experiments/pose_mask_variants.py [--scenes 10] [--seeds 0,1] \\
        [--variants 0.5/2,0.4/2,0.6/2,0.5/1,0.5/3,0.4/3,rim:2/5/0.5] [--scan DIR]      # needs ../shared/data
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import service.pipeline.prepare as prepare  # noqa: E402
import service.preprocess.localisation as localisation  # noqa: E402
import service.preprocess.localise as localise  # noqa: E402
from model_export.experiments.real_scan_poses import compare, read_scan  # noqa: E402
from model_export.localiser.evaluate import REAL_SCANS  # noqa: E402
from model_export.localiser.pose_accuracy import pose_estimator  # noqa: E402
from model_export.localiser.pose_accuracy import pose_accuracy, validation_scenes  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator  # noqa: E402
from service.io.volume import Volume  # noqa: E402
from service.preprocess.stack import StackSlices, slice_axis_of, split_stack  # noqa: E402

MIN_KEPT = 0.3
"""A slice whose image-cut mask keeps less than this share of the mask inset by the edge alone keeps
that inset mask (a cap of the brain is mostly partial volume with the CSF)."""


def image_rim(image: NDArray, region: NDArray, spacing: NDArray, axis: int | None = None, edge_mm: float = 2.0,
              depth_mm: float = 5.0, bright: float = 0.5) -> NDArray[np.bool_]:
    """``region`` less its outer ``edge_mm`` and the pixels joined to that edge, in the plane of each
    slice, that are CSF-bright or skull-dark within ``depth_mm`` of the outside: bright beyond
    ``bright`` of the way from the brain's median (``region`` inset by 5 mm) to ``region``'s 98th
    percentile, dark below half the median. Holes are filled and single-pixel spurs opened away.

    Example (a tissue disk inside a bright ring, the region reaching past the ring: the ring goes):
        >>> yy, xx = np.mgrid[-20:21, -20:21]
        >>> r = np.hypot(yy, xx)[..., None].repeat(3, axis=2)
        >>> image = np.where(r <= 12, 100.0, np.where(r <= 15, 300.0, 50.0)).astype(np.float32)
        >>> out = image_rim(image, r <= 16, np.array([1.0, 1.0, 3.0]), edge_mm=1.0)
        >>> bool(out[..., 1][r[..., 1] <= 11].all()), bool(out[..., 1][r[..., 1] > 13].any())
        (True, False)
    """
    region = np.asarray(region, bool)
    if not region.any():
        return region
    axis = slice_axis_of(spacing) if axis is None else axis
    image = np.asarray(image, np.float32)
    core = localisation.inset_in_plane(region, spacing, 5.0, axis)
    tissue = float(np.median(image[core if core.sum() >= 50 else region]))
    csf = float(np.percentile(image[region], 98))
    rim_like = (image > tissue + bright * (csf - tissue)) | (image < 0.5 * tissue)
    inside_edge = localisation.inset_in_plane(region, spacing, edge_mm, axis)
    band = region & ~localisation.inset_in_plane(region, spacing, depth_mm, axis)
    plane = np.zeros((3, 3, 3), bool)
    for ax in (a for a in range(3) if a != axis):
        line = [1, 1, 1]
        line[ax] = slice(None)
        plane[tuple(line)] = True
    edge = region & ~inside_edge
    rim = ndimage.binary_propagation(edge, structure=plane, mask=edge | (band & rim_like))
    brain = ndimage.binary_opening(region & ~rim, structure=plane)
    brain = np.moveaxis(np.stack([ndimage.binary_fill_holes(s) for s in np.moveaxis(brain, axis, 0)]), 0, axis)
    kept, inset = (np.moveaxis(m, axis, 0).reshape(region.shape[axis], -1).sum(1) for m in (brain, inside_edge))
    weak = kept < MIN_KEPT * inset
    np.moveaxis(brain, axis, 0)[weak] = np.moveaxis(inside_edge, axis, 0)[weak]
    return brain


def rim_split(edge_mm: float, depth_mm: float, bright: float):  # noqa: ANN201
    """``split_stack`` with the pose mask cut by :func:`image_rim` in the stack's N4-corrected image."""
    def split(volume: Volume, mask: NDArray, axis: int | None = None) -> StackSlices:
        return split_stack(volume, image_rim(volume.array, mask, volume.spacing, axis, edge_mm, depth_mm, bright), axis)
    return split


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=10)
    ap.add_argument("--seeds", default="0,1", help="the draws of each real-scan pair")
    ap.add_argument("--variants", default="0.5/2,0.4/2,0.6/2,0.5/1,0.5/3,0.4/3",
                    help="CUT/INSET_MM or rim:EDGE/DEPTH/HI, comma-separated")
    ap.add_argument("--scan", type=Path, default=REAL_SCANS / "mial_lausanne_t30", help="a real scan with manual masks")
    args = ap.parse_args()
    estimator, localiser = pose_estimator(), localise.default_localiser()
    scenes = validation_scenes(args.scenes)
    volumes, manual = read_scan(args.scan)
    shipped = localisation.THRESHOLD
    for variant in args.variants.split(","):
        if variant.startswith("rim:"):
            edge, depth, bright = (float(x) for x in variant[4:].split("/"))
            localisation.THRESHOLD, localisation.POSE_MASK_INSET_MM = shipped, 0.0
            prepare.split_stack = rim_split(edge, depth, bright)
        else:
            cut, inset = (float(x) for x in variant.split("/"))
            localisation.THRESHOLD, localisation.POSE_MASK_INSET_MM = cut, inset
            prepare.split_stack = split_stack
        acc = pose_accuracy(scenes, estimator, localiser, ("localiser",))["localiser"] if scenes else None
        pairs = []
        for seed in (int(s) for s in args.seeds.split(",")):
            with contextlib.redirect_stdout(io.StringIO()):        # compare() prints per stack
                pairs.append(compare(volumes, manual, localiser, OnnxPoseEstimator(estimator.model.with_seed(seed))))
        real = "; ".join(f"{p['median_ed_mm']:.2f} mm, turn {p['offset_deg']:.1f} deg" if p else "none accepted in both"
                         for p in pairs)
        on_scenes = "no scenes" if acc is None else (f"scenes {acc['median_ed_mm']:.2f} / {acc['mean_ed_mm']:.2f} mm, "
                                                     f"twin-min mean {acc['mean_twin_min_mm']:.2f}")
        print(f"{variant}: {on_scenes} | {args.scan.name} without against with masks: {real}", flush=True)


if __name__ == "__main__":
    main()
