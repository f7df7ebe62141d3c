"""The brain localiser on held-out whole-uterus scenes whose fetal head moves as in the pose benchmarks.

The localiser's own held-out sets move the head by the scene generator's drift and single-slice
jumps. Here the same scenes (the validation brains, the held-out style, T2-like contrast, the same
seeds) are drawn again with the head moving as each motion level of the pose benchmarks
(``model_export.acquisitions``: mild, moderate, jumps, independent) over an interleaved acquisition,
where neighbouring slices are acquired half a stack apart in time. Printed per level: Dice (median,
mean, minimum), how many brain slices (true brain over :data:`BRAIN_SLICE_MM2`) the mask mostly
misses (under half of the slice's brain), and of those how many the network itself found (its
probability over 0.5 on at least half of the slice's brain), so that the rest were lost to the
stack's geometry (:mod:`service.preprocess.brain_shape`). Needs ``../shared/data`` (the atlas
volumes).

    .venv/bin/python model_export/experiments/localiser_motion.py [--scenes 24] [--model M]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes, split  # noqa: E402
from model_export.localiser.evaluate import dice  # noqa: E402
from model_export.localiser.scenes import MOTIONS, HeadModel, synth_scene  # noqa: E402
from service.preprocess.brain_shape import THRESHOLD  # noqa: E402
from service.preprocess.localise import Localiser, default_localiser  # noqa: E402

BRAIN_SLICE_MM2 = 300.0
"""A slice whose true brain (skull inside) covers less is a cap of the brain, not counted."""
FIRST_SEED = 5_000_000


def scene_scores(localiser: Localiser, scene) -> tuple[float, int, int, int]:  # noqa: ANN001
    """The mask's Dice on ``scene``, and of its brain slices: how many, how many the mask mostly
    misses, and how many of those the network found before the geometry (one network run)."""
    truth = scene.mask
    prob, grid = localiser.probabilities(scene.volume)
    found = localiser.settle(scene.volume, prob, grid).mask
    network = grid.to_stack(prob) >= THRESHOLD
    per_slice = lambda m: (m & truth).reshape(-1, truth.shape[2]).sum(0)         # noqa: E731
    true_area = truth.reshape(-1, truth.shape[2]).sum(0)
    brain = true_area * scene.volume.spacing[0] * scene.volume.spacing[1] > BRAIN_SLICE_MM2
    missed = brain & (per_slice(found) < 0.5 * true_area)
    return (dice(found, truth), int(brain.sum()), int(missed.sum()),
            int((missed & (per_slice(network) >= 0.5 * true_area)).sum()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=24, help="scenes per motion level (the same seeds for each)")
    ap.add_argument("--model", type=Path, help="a localiser ONNX file (default: the shipped one)")
    args = ap.parse_args()
    if not DEFAULT_ATLAS_ROOT.exists():
        sys.exit(f"needs the atlas volumes at {DEFAULT_ATLAS_ROOT}")
    localiser = Localiser.load(args.model) if args.model else default_localiser()
    heads = [HeadModel.from_arrays(v.image, v.mask, v.affine)
             for v in load_volumes(split(DEFAULT_ATLAS_ROOT)[1], DEFAULT_ATLAS_ROOT)]
    for motion in (None, *MOTIONS):
        scores, counts = [], np.zeros(3, int)
        for i in range(args.scenes):
            scene = synth_scene(heads[i % len(heads)], np.random.default_rng(FIRST_SEED + i), "heldout",
                                random_contrast=False, motion=motion)
            score, *slices = scene_scores(localiser, scene)
            scores.append(score)
            counts += slices
        d = np.array(scores)
        label = motion or "the generator's own drift"
        print(f"{label}: Dice median {np.median(d):.3f} mean {d.mean():.3f} min "
              f"{d.min():.3f}; brain slices mostly missed {counts[1]} of {counts[0]} "
              f"({100 * counts[1] / max(counts[0], 1):.1f} %), of which the network found {counts[2]}", flush=True)


if __name__ == "__main__":
    main()
