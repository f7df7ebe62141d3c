"""Simulated acquisitions of a real brain: a job's reconstruction of a real scan as the source
volume, beside a held-out atlas brain, through ``/v1/predict``'s stages.

The benchmarks simulate acquisitions from the atlas volumes, which are population averages:
smoother than any one brain. Here the source is a real fetus's brain as a job reconstructs it
(atlas space, 0.8 mm; its brain mask from its own intensities, :func:`brain_mask`), cut by the same
simulator with known poses. Per acquisition it prints the image stage's mismatch before and after
(per weighted point, in units of its noise: what ``request_mismatch.py`` compares across caches and
real scans), the median and mean twin-min E.D. against the truth, the slices accepted and those over
10 mm accepted, and the acquisition's common error (rotation vector in degrees and shift, about the
slices' centre; :func:`~model_export.experiments.frame_bias.common_frame`) with the median E.D. once
it is undone. The truth of the real brain is where the job placed it in the atlas, so its common
error is where the network and the job's frame steps disagree.

    D=../shared/data/real_scans/mial_lausanne_t30; svrnet reconstruct $D/{axial,coronal,sagittal}1_lr.nii.gz \\
        -m $D/axial1_lr_brain_mask.nii.gz -m $D/coronal1_lr_brain_mask.nii.gz -m $D/sagittal1_lr_brain_mask.nii.gz \\
        --masks-hold-csf --out recon.nii.gz
    .venv/bin/python model_export/experiments/real_brain_acquisitions.py recon.nii.gz [--atlas STA31] \\
        [--levels mild,moderate,jumps] [--repeats 2] [--seed 5]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.acquisitions import simulate_acquisition  # noqa: E402
from model_export.atlas import DEFAULT_ATLAS_ROOT, AtlasVolume, load_volumes, split  # noqa: E402
from model_export.evaluate_acquisitions import prepare_acquisition  # noqa: E402
from model_export.experiments.frame_bias import common_frame  # noqa: E402
from service.geometry import se3, twin  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator  # noqa: E402
from service.inference.model_file import load_model  # noqa: E402
from service.io.volume import read_volume  # noqa: E402
import service.pipeline.predict as pipeline  # noqa: E402

BRAIN_FRACTION = 0.15
"""A reconstruction's brain: voxels brighter than this fraction of its median positive intensity."""


def brain_mask(volume: NDArray) -> NDArray[np.bool_]:
    """The brain of a reconstruction (zero where no slice reached): its voxels over
    :data:`BRAIN_FRACTION` of the median positive intensity, opened twice, the largest component,
    holes filled.

    Example (a cube with a dark voxel inside, and a bright speck apart; the opening rounds its edges):
        >>> v = np.zeros((20, 20, 20)); v[5:15, 5:15, 5:15] = 100.0; v[9, 9, 9] = 0.0; v[0, 0, 0] = 100.0
        >>> m = brain_mask(v); bool(m[7:13, 7:13, 7:13].all()), bool(m[0, 0, 0]), bool(m[4:16, 4:16, 4:16].sum() == m.sum())
        (True, False, True)
    """
    arr = np.asarray(volume, np.float64)
    positive = arr[arr > 0]
    if not positive.size:
        return np.zeros(arr.shape, bool)
    mask = ndimage.binary_opening(arr > BRAIN_FRACTION * float(np.median(positive)), iterations=2)
    labels, count = ndimage.label(mask)
    if not count:
        return mask
    largest = 1 + int(np.argmax(ndimage.sum(mask, labels, range(1, count + 1))))
    return ndimage.binary_fill_holes(labels == largest)


def source_volumes(paths: list[Path]) -> list[AtlasVolume]:
    """Volumes to simulate from instead of the atlas brains: each file (atlas space: a job's
    reconstruction) with its brain from its own intensities (:func:`brain_mask`)."""
    out = []
    for path in paths:
        vol = read_volume(path)
        out.append(AtlasVolume(path.name.split(".")[0], "source", vol.array.astype(np.float32),
                               brain_mask(vol.array).astype(np.float32), vol.affine))
    return out


def acquisition_line(name: str, level: str, stacks: list, model, estimator) -> str:  # noqa: ANN001
    """One simulated acquisition through the stages, as a line (see the module)."""
    info = model.info
    prepared, truth = prepare_acquisition(stacks, info)
    parts, _ = pipeline.estimate_stacks(prepared, estimator, 100)
    predictions = pipeline.predict_from_estimates(prepared, parts, info, info.variance_threshold)[0]
    stage = next((p.poses.image_consistency for p in predictions if p.poses.image_consistency is not None), None)
    final, true = np.concatenate([p.poses.poses for p in predictions]), np.concatenate(truth)
    e = twin.twin_min_ed(final, true, info.symmetry_plane_x_mm)
    accepted = np.concatenate([np.array([r is None for r in p.reasons]) for p in predictions])
    near = twin.nearer(final, true, info.symmetry_plane_x_mm)
    frame, undone = common_frame(final, near, near[:, :3, 3].mean(axis=0))
    mismatch = "no image stage" if stage is None else f"mismatch {stage.mismatch_before:.2f} -> {stage.mismatch_after:.2f}"
    return (f"{name} {level}: {mismatch}; twin-min median {np.median(e):.1f} / mean {e.mean():.1f} mm, accepted "
            f"{accepted.sum()}/{len(accepted)}, over 10 mm accepted {(accepted & (e > 10)).sum()}; common error "
            f"{np.round(np.degrees(se3.so3_log(frame[:3, :3])), 1).tolist()} deg, {np.round(frame[:3, 3], 1).tolist()} mm; "
            f"undone {np.median(undone):.2f} mm")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("volume", type=Path, help="a job's reconstruction (atlas space)")
    ap.add_argument("--atlas", default="STA31", help="a held-out atlas brain beside it")
    ap.add_argument("--levels", default="mild,moderate,jumps")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--model", type=Path, default=Path("service/models/default/model.onnx"))
    args = ap.parse_args()
    model = load_model(args.model)
    estimator = OnnxPoseEstimator(model)
    sources = source_volumes([args.volume])
    sources += [v for v in load_volumes(split(DEFAULT_ATLAS_ROOT)[1], DEFAULT_ATLAS_ROOT) if v.name == args.atlas]
    rng = np.random.default_rng(args.seed)
    for source, name in zip(sources, ["real brain", args.atlas]):
        for level in args.levels.split(","):
            for _ in range(args.repeats):
                stacks = simulate_acquisition(source.image, source.mask, source.affine, rng, level)
                print(acquisition_line(name, level, stacks, model, estimator), flush=True)


if __name__ == "__main__":
    main()
