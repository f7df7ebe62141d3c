"""Where a real brain's answer places it in the atlas, against age-matched atlas templates.

A real scan has no true poses, but the atlas space is the atlas volumes' own: a real brain's place
in it is, up to the anatomy of one brain against another, where a rigid registration to an atlas
volume of its age puts it. For each answer of ``/v1/predict`` (with the scan's manual masks, and
without masks) this script splats the slices both answers accept (the manual masks' pixels, so
that the two volumes differ only by the poses) into a Gaussian average at that answer's poses,
registers it rigidly to each atlas volume of ``--volumes`` (brain-masked; normalised correlation,
three levels, about the template brain's centre) and prints the correlation reached and the
registration's rotation and shift: the correction the answer's placement needs by that template.
Registrations to neighbouring ages disagree with one another by a few degrees and millimetres
(docs/accuracy.md, "What a held-out brain's error is made of"): compare the two answers by the
same template, and read single figures with that spread in mind.

``--job-volume FILE`` registers a reconstruction job's volume (``svrnet reconstruct --out``, atlas
space) instead, from starts turned 0 and +-``--start-deg`` about each axis in turn (0: the unturned
start alone): whether the registration finds one optimum whatever its start, and whether templates
agree on it.

    .venv/bin/python model_export/experiments/template_placement.py SCAN_FOLDER --volumes STA30,STA32,STA34 [--localiser M]
    .venv/bin/python model_export/experiments/template_placement.py --job-volume recon.nii.gz --volumes STA30,SB_GA30_operated
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.atlas import load_volumes  # noqa: E402
from model_export.experiments.real_scan_poses import answer, read_scan  # noqa: E402
from model_export.localiser.pose_accuracy import pose_estimator  # noqa: E402
from service.geometry import se3  # noqa: E402
from service.io.volume import Volume, read_volume, to_sitk  # noqa: E402
from service.preprocess.localise import Localiser, default_localiser  # noqa: E402
from service.reconstruction.gaussian_average import gaussian_average  # noqa: E402
from service.reconstruction.grid import Grid  # noqa: E402
from service.reconstruction.midline import registration_method  # noqa: E402
from service.reconstruction.slices import SliceSet  # noqa: E402


def splatted(answers: list[list[dict]], which: int, volumes: dict[str, Volume], manual: dict[str, Volume],
             grid: Grid) -> tuple[Volume, int]:
    """The Gaussian average of the slices every answer accepts, at answer ``which``'s poses, and their count."""
    stacks = []
    for k, name in enumerate(volumes):
        both = np.array([all(a[k]["slices"][s]["accepted"] for a in answers) for s in range(len(answers[0][k]["slices"]))])
        poses = np.array([s["atlas_from_voxel"] for s in answers[which][k]["slices"]], np.float64)
        stacks.append((volumes[name], manual[name].array > 0, poses, both))
    slices = SliceSet.from_stacks(stacks)
    average = gaussian_average(slices, slices.atlas_from_voxel, grid)
    return Volume(average.volume, grid.affine), int(slices.include.sum())


def register(moving: Volume, template: Volume, template_mask: NDArray[np.bool_],
             start_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> tuple[float, float, float]:
    """Rigid registration of ``moving`` to the brain-masked ``template``, from a start turned by
    ``start_deg`` (Euler angles about the template brain's centre): (correlation reached, rotation
    in degrees, shift of the template brain's centre in mm)."""
    import SimpleITK as sitk

    fixed = sitk.Cast(to_sitk(Volume((template.array * template_mask).astype(np.float32), template.affine)),
                      sitk.sitkFloat32)
    image = sitk.Cast(to_sitk(Volume(moving.array.astype(np.float32), moving.affine)), sitk.sitkFloat32)
    centre = np.argwhere(template_mask).mean(axis=0)
    transform = sitk.Euler3DTransform()
    transform.SetCenter(fixed.TransformContinuousIndexToPhysicalPoint([float(c) for c in centre]))
    transform.SetRotation(*(float(np.radians(a)) for a in start_deg))
    method = registration_method(sampling=0.2, iterations=300, relaxation=0.7, finest_sigma_mm=0.0)
    method.SetInitialTransform(transform, inPlace=True)
    method.Execute(fixed, image)
    rotation = np.array(transform.GetMatrix()).reshape(3, 3)
    return (-float(method.GetMetricValue()), float(np.degrees(np.linalg.norm(se3.so3_log(rotation)))),
            float(np.linalg.norm(transform.GetTranslation())))


def register_job_volumes(files: list[Path], templates: list, start_deg: float) -> None:
    """Each job volume registered to each template from the unturned start and starts turned by
    +-``start_deg`` about each axis: the correction found from each, in degrees and mm."""
    starts = [(0.0, 0.0, 0.0)] + ([tuple(sign * start_deg * (k == axis) for k in range(3))
                                   for axis in range(3) for sign in (1, -1)] if start_deg else [])
    for path in files:
        volume = read_volume(path)
        for template in templates:
            found = [register(volume, Volume(template.image, template.affine), template.mask > 0, start)
                     for start in starts]
            degrees, shifts = np.array([f[1] for f in found]), np.array([f[2] for f in found])
            print(f"{path.name} by {template.name}: correlation {found[0][0]:.3f}; correction {degrees[0]:.2f} deg, "
                  f"{shifts[0]:.2f} mm; over {len(starts)} starts {degrees.min():.2f}-{degrees.max():.2f} deg, "
                  f"{shifts.min():.2f}-{shifts.max():.2f} mm", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scan", type=Path, nargs="?", help="a real scan folder with manual masks")
    ap.add_argument("--volumes", required=True, help="comma-separated atlas volumes, e.g. STA30,STA32")
    ap.add_argument("--localiser", type=Path, help="a localiser ONNX file (default: the shipped one)")
    ap.add_argument("--job-volume", type=Path, action="append", help="a job's volume in atlas space; repeat")
    ap.add_argument("--start-deg", type=float, default=8.0, help="the starts' turn for --job-volume (0: one start)")
    args = ap.parse_args()
    templates = load_volumes(args.volumes.split(","))
    if not templates:
        sys.exit(f"none of {args.volumes} found in the atlas data")
    if args.job_volume:
        register_job_volumes(args.job_volume, templates, args.start_deg)
        return
    if args.scan is None:
        ap.error("a scan folder, or --job-volume")
    localiser = Localiser.load(args.localiser) if args.localiser else default_localiser()
    estimator = pose_estimator()
    volumes, manual = read_scan(args.scan)
    answers = [answer(volumes, m, localiser, estimator)[0] for m in (manual, None)]
    grid = Grid(templates[0].affine, tuple(templates[0].image.shape))
    for which, label in enumerate(("manual masks", "no masks")):
        volume, n = splatted(answers, which, volumes, manual, grid)
        for template in templates:
            ncc, degrees, shift = register(volume, Volume(template.image, template.affine), template.mask > 0)
            print(f"{label:12s} ({n} slices) by {template.name}: correlation {ncc:.3f}; correction {degrees:.2f} deg, "
                  f"{shift:.2f} mm", flush=True)


if __name__ == "__main__":
    main()
