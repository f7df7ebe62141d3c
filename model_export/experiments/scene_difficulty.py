"""Why whole-uterus scenes are posed less accurately than the pose benchmarks' acquisitions.

The same validation brains, three stacks a request at mild motion, the pose network's own (atlas)
brain mask, every slice with :data:`~model_export.localiser.pose_accuracy.MIN_BRAIN_PIXELS` of
brain scored against its true pose (:func:`~model_export.localiser.pose_accuracy.score_scene`):

* ``scenes``: the generated whole-uterus scenes (:func:`~model_export.localiser.pose_accuracy.validation_cases`;
  ``--planning``: the stacks' orientations about the head);
* ``scenes-atlas-image``: the same stacks, each slice's image replaced by the atlas volume sampled at
  its true pose with the acquisitions' slice profile (no noise, bias, CSF or contrast of the scene:
  what the image content costs);
* ``acquisitions``: the pose benchmarks' stacks (:func:`~model_export.acquisitions.simulate_acquisition`)
  with ``--orientations`` ``standard`` (axial, coronal, sagittal to the head, tilted about 10 deg),
  ``orthogonal`` (three orthogonal stacks turned together at random) or ``independent`` (each stack
  its own random orientation), ``--pixel-mm`` and ``--gap-mm`` as scanners set them.

``--alone`` sends each stack in a request of its own; ``--raw`` turns the stack stage off and scores
the network's own MC means against the nearer twin (the stage's gain is the difference). Printed:
the slices, median and mean E.D., and each request's median. Needs ``../shared/data``.

    .venv/bin/python model_export/experiments/scene_difficulty.py scenes [--planning orthogonal] [--requests 6]
    .venv/bin/python model_export/experiments/scene_difficulty.py acquisitions --orientations independent [--alone] [--raw]
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.acquisitions import ORIENTATIONS, simulate_acquisition  # noqa: E402
from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes, split  # noqa: E402
from model_export.localiser import pose_accuracy  # noqa: E402
from model_export.localiser.pose_accuracy import pose_estimator  # noqa: E402
from model_export.localiser.scenes import Scene  # noqa: E402
from model_export.localiser.surroundings import random_rotation  # noqa: E402
from service.geometry import sampling  # noqa: E402
from service.io.volume import Volume  # noqa: E402
from service.pipeline.predict import predict  # noqa: E402
from service.preprocess.stack import split_stack  # noqa: E402

ORIENTATION_CHOICES = ("standard", "orthogonal", "independent")


def atlas_image(scene: Scene, volume) -> Scene:  # noqa: ANN001
    """``scene`` with each slice's image the atlas ``volume`` sampled at the slice's true pose (slice
    profile of the scene's slice spacing), its masks and poses unchanged."""
    shape = scene.volume.array.shape
    layout = split_stack(Volume(np.zeros(shape, np.float32), scene.volume.affine), np.ones(shape, bool))
    poses = scene.atlas_from_voxel @ np.linalg.inv(layout.slice_from_voxel)
    images = sampling.sample_slices(volume.image, volume.affine, poses, shape[0], float(scene.volume.spacing[0]),
                                    thickness_mm=float(scene.volume.spacing[2]))
    array = np.ascontiguousarray(layout.to_stack(images)).astype(np.float32) * 1000.0
    return replace(scene, volume=replace(scene.volume, array=array))


def acquisition(volume, rng: np.random.Generator, orientations: str, **geometry: float) -> list[Scene]:  # noqa: ANN001
    """Three stacks of ``volume`` at mild motion (:func:`~model_export.acquisitions.simulate_acquisition`),
    their axes as ``orientations`` says (drawn from a child of ``rng``: the acquisition's own draws
    are those of ``standard``)."""
    plan = rng.spawn(1)[0]
    turn = random_rotation(plan)
    axes = {"standard": None, "orthogonal": [turn @ ORIENTATIONS[o] for o in ORIENTATIONS],
            "independent": [random_rotation(plan) for _ in ORIENTATIONS]}[orientations]
    stacks = simulate_acquisition(volume.image, volume.mask, volume.affine, rng, "mild", axes=axes, **geometry)
    return [Scene(s.volume, s.mask.array > 0, s.mask.array > 0, s.atlas_from_voxel) for s in stacks]


def requests_of(source: str, count: int, planning: str = "independent", orientations: str = "standard",
                pixel_mm: float = 1.0, gap_mm: float = 3.0) -> list[list[Scene]]:
    """``count`` requests of three stacks of the validation brains at mild motion, as ``source`` says
    (the module docstring's sources): scenes planned as ``planning`` says, or acquisitions with
    ``orientations``, ``pixel_mm`` and ``gap_mm`` (a 128 mm field of view)."""
    volumes = load_volumes(split(DEFAULT_ATLAS_ROOT)[1], DEFAULT_ATLAS_ROOT)
    if source == "acquisitions":
        size = int(round(128 * 1.0 / pixel_mm))
        return [acquisition(volumes[i % len(volumes)], np.random.default_rng(300 + i), orientations,
                            pixel_mm=pixel_mm, size=size, gap_mm=gap_mm, thickness_mm=gap_mm) for i in range(count)]
    cases = pose_accuracy.validation_cases(count, stacks=3, motion="mild", planning=planning)
    if source == "scenes-atlas-image":
        cases = [[atlas_image(s, volumes[i % len(volumes)]) for s in case] for i, case in enumerate(cases)]
    return cases


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("source", choices=("scenes", "scenes-atlas-image", "acquisitions"))
    ap.add_argument("--requests", type=int, default=6)
    ap.add_argument("--planning", default="independent", choices=pose_accuracy.PLANNINGS)
    ap.add_argument("--orientations", default="standard", choices=ORIENTATION_CHOICES)
    ap.add_argument("--pixel-mm", type=float, default=1.0)
    ap.add_argument("--gap-mm", type=float, default=3.0)
    ap.add_argument("--alone", action="store_true", help="each stack in a request of its own")
    ap.add_argument("--raw", action="store_true", help="the stack stage off; twin-min of the network's MC means")
    args = ap.parse_args()
    if args.source == "acquisitions" and args.planning != "independent":
        ap.error("--planning is the scenes' (the acquisitions' stacks: --orientations)")
    if args.source != "acquisitions" and (args.orientations != "standard" or args.pixel_mm != 1.0 or args.gap_mm != 3.0):
        ap.error("--orientations, --pixel-mm and --gap-mm are the acquisitions' (the scenes draw their own)")

    cases = requests_of(args.source, args.requests, args.planning, args.orientations, args.pixel_mm, args.gap_mm)
    if args.raw:
        pose_accuracy.predict = lambda prepared, est, mc, thr: predict(prepared, est, mc, thr, stack_consistency=False)
    estimator, key = pose_estimator(), "ed_min" if args.raw else "ed"
    errors, per_request = [], []
    for case in cases:
        requests = [[s] for s in case] if args.alone else [case]
        got = np.concatenate([pose_accuracy.score_scene(r, "brain", estimator)[key] for r in requests])
        got = got[np.isfinite(got)]
        errors.append(got)
        per_request.append(round(float(np.median(got)), 1))
    e = np.concatenate(errors)
    print(f"{args.source} slices {len(e)} median {np.median(e):.2f} mean {np.mean(e):.2f} mm; per request {per_request}")


if __name__ == "__main__":
    main()
