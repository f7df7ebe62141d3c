"""Which part of the brain's outline turns a real scan's answer: the manual masks with the
localiser's outline swapped in over one region of the brain at a time.

Without masks, the shared real scan's ``/v1/predict`` answer lies turned by 3.5-5° from the answer
with its manual masks, mostly about the atlas x axis (``mask_vote.py``, ``predict_midline.py``), and
no weighting of whole slices brings the two together. Here every stack keeps its manual mask except
in one region of the brain, where the localiser's mask (the skull's inside, as the service cuts it)
takes its place: the brain split in thirds along the atlas's inferior-superior (z) and
anterior-posterior (y) axes, each voxel placed in the atlas by the manual answer's pose of its slice.
Both masks are sent as holding the CSF (``masks_hold_csf``: the 2 mm inset on both), so only the
outline differs. Beside them, the manual masks grown and inset by ``--margin`` mm everywhere, and the
localiser's grown so (the two conventions differ by about a pixel on this scan,
docs/reports/localiser-experiments.md), show what a uniform change of extent does. Per variant and seed of the model's fixed draws: the median E.D. from the manual
answer over the slices both accept, and their common rigid offset as a rotation vector (degrees,
atlas axes) and a shift (mm) about the brain's centre.

    .venv/bin/python model_export/experiments/mask_regions.py [SCAN_FOLDER] [--seeds 0,1]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.experiments.mask_vote import accepted_in_both, common_offset  # noqa: E402
from model_export.experiments.real_scan_poses import read_scan  # noqa: E402
from model_export.localiser.evaluate import REAL_SCANS  # noqa: E402
from model_export.localiser.pose_accuracy import pose_estimator  # noqa: E402
from service.pipeline.documents import stack_objects  # noqa: E402
from service.geometry import anchors, se3  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator  # noqa: E402
from service.io.volume import Volume  # noqa: E402
from service.pipeline.predict import predict  # noqa: E402
from service.pipeline.prepare import StackUpload, prepare_stacks  # noqa: E402
from service.preprocess.localisation import grown, inset_in_plane  # noqa: E402
from service.preprocess.localise import default_localiser  # noqa: E402

REGIONS = {"z<1/3": (2, 0), "z mid": (2, 1), "z>2/3": (2, 2), "y<1/3": (1, 0), "y mid": (1, 1), "y>2/3": (1, 2)}
"""Each region: the atlas axis (1: y, anterior-posterior; 2: z, inferior-superior) and its third of the brain."""


def atlas_coordinates(shape: tuple[int, ...], atlas_from_voxel: NDArray, axis: int) -> NDArray[np.float64]:
    """``[*shape, 3]`` each voxel's atlas position, its slice (along ``axis``) placed by that slice's
    ``atlas_from_voxel [n, 4, 4]``.

    Example (two slices along the last axis, the second shifted 10 mm in z):
        >>> a = np.stack([np.eye(4), np.eye(4)]); a[1, 2, 3] = 10.0
        >>> atlas_coordinates((2, 2, 2), a, 2)[1, 1, 1].tolist()
        [1.0, 1.0, 11.0]
    """
    out = np.zeros((*shape, 3))
    plane_shape = [s for d, s in enumerate(shape) if d != axis]
    plane = np.stack(np.meshgrid(*[np.arange(s, dtype=np.float64) for s in plane_shape], indexing="ij"), axis=-1)
    for k in range(shape[axis]):
        voxel = np.insert(plane, axis, float(k), axis=-1)                     # [..., 3] this slice's voxels
        np.moveaxis(out, axis, 0)[k] = voxel @ atlas_from_voxel[k, :3, :3].T + atlas_from_voxel[k, :3, 3]
    return out


def hybrid(manual: NDArray, found: NDArray, where: NDArray, axis: int, third: int) -> NDArray[np.uint8]:
    """The manual mask with ``found`` in its place over the ``third`` (0, 1, 2) of the brain along
    atlas ``axis`` (``where [..., 3]`` each voxel's atlas position; the thirds of the manual brain's extent).

    Example:
        >>> where = np.zeros((3, 1, 1, 3)); where[:, 0, 0, 2] = [0.0, 5.0, 10.0]
        >>> hybrid(np.ones((3, 1, 1)), np.zeros((3, 1, 1)), where, 2, 0).ravel().tolist()
        [0, 1, 1]
    """
    inside = where[..., axis][manual > 0]
    lo, hi = float(inside.min()), float(inside.max())
    cuts = lo + (hi - lo) * np.array([0.0, 1 / 3, 2 / 3, 1.0])
    band = (where[..., axis] >= cuts[third]) & (where[..., axis] <= cuts[third + 1])
    return np.where(band, found > 0, manual > 0).astype(np.uint8)


def answer(volumes: dict[str, Volume], masks: dict[str, NDArray], estimator) -> tuple[list[dict], list]:  # noqa: ANN001
    """``/v1/predict``'s stacks with ``masks`` sent as holding the CSF."""
    uploads = [StackUpload(n, volumes[n], Volume(masks[n], volumes[n].affine), f"{n}_mask", mask_holds_csf=True)
               for n in volumes]
    prepared = prepare_stacks(uploads, estimator.info, True, workers=2)
    return stack_objects(predict(prepared, estimator, 100, estimator.info.variance_threshold)[0]), prepared


def agreement(reference: tuple[list[dict], list], other: tuple[list[dict], list]) -> str:
    """The two answers over the slices both accept: median E.D. and common rigid offset, as a line."""
    joined = common_offset(accepted_in_both(reference[0], other[0], reference[1]))
    if joined is None:
        return "no slice accepted in both"
    a, b, frame, _ = joined
    return (f"{len(a)} slices, median {np.median(anchors.ed(a, b)):.2f} mm; common "
            f"{np.round(np.degrees(se3.so3_log(frame[:3, :3])), 1).tolist()} deg, {np.round(frame[:3, 3], 1).tolist()} mm")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scan", type=Path, nargs="?", default=REAL_SCANS / "mial_lausanne_t30")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--margin", type=float, default=1.2, help="mm the manual masks are grown and inset by (one pixel or more)")
    args = ap.parse_args()
    base = pose_estimator(None)
    volumes, manual_volumes = read_scan(args.scan)
    manual = {n: manual_volumes[n].array > 0 for n in volumes}
    found = {n: default_localiser().localise(volumes[n]).mask for n in volumes}
    for seed in (int(s) for s in args.seeds.split(",")):
        estimator = base if seed == 0 else OnnxPoseEstimator(base.model.with_seed(base.model.mc_seed + seed))
        reference = answer(volumes, {n: manual[n].astype(np.uint8) for n in volumes}, estimator)
        where = {}
        for (n, vol), st in zip(volumes.items(), reference[0]):
            axis = st["slice_axis"]
            where[n] = atlas_coordinates(vol.array.shape, np.array([s["atlas_from_voxel"] for s in st["slices"]]), axis)
        print(f"seed {seed}, the localiser's masks everywhere: "
              f"{agreement(reference, answer(volumes, {n: found[n].astype(np.uint8) for n in volumes}, estimator))}",
              flush=True)
        for sign, label in ((1.0, "grown"), (-1.0, "inset")):
            masks = {n: (grown if sign > 0 else inset_in_plane)(manual[n], np.asarray(volumes[n].spacing), args.margin)
                     .astype(np.uint8) for n in volumes}
            print(f"seed {seed}, the manual masks {label} by {args.margin} mm: {agreement(reference, answer(volumes, masks, estimator))}",
                  flush=True)
        masks = {n: grown(found[n], np.asarray(volumes[n].spacing), args.margin).astype(np.uint8) for n in volumes}
        print(f"seed {seed}, the localiser's masks grown by {args.margin} mm: {agreement(reference, answer(volumes, masks, estimator))}",
              flush=True)
        for label, (axis, third) in REGIONS.items():
            masks = {n: hybrid(manual[n], found[n], where[n], axis, third) for n in volumes}
            print(f"seed {seed}, the localiser's outline over {label}: {agreement(reference, answer(volumes, masks, estimator))}",
                  flush=True)


if __name__ == "__main__":
    main()
