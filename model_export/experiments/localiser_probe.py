"""What a localiser looks for: one real stack with a manual mask, its image changed around the mask.

Each probe changes the stack and runs the localiser again; the Dice against the manual mask and the
recall of the slices where the localiser misses most tell what the network relies on. A network that
recovers a missed head when a fluid ring is painted around it, and loses it when the brain is darkened
or its surroundings brightened, has learnt "a brain is ringed by fluid, or brighter than what surrounds
it" (docs/reports/localiser-experiments.md). Needs ``../shared/data/real_scans`` (or a stack and mask given).

    .venv/bin/python model_export/experiments/localiser_probe.py [--model service/localisers/default/model.onnx] \
        [--stack ../shared/data/real_scans/mial_lausanne_t30/sagittal1_lr.nii.gz]
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.localiser.evaluate import REAL_SCANS, dice  # noqa: E402
from service.core.settings import DEFAULT_LOCALISERS_DIR  # noqa: E402
from service.io.volume import Volume, read_volume  # noqa: E402
from service.preprocess.localise import Localiser  # noqa: E402
from service.preprocess.stack import slice_axis_of  # noqa: E402

RING_MM, FAR_MM = 4.5, 9.0


def probes(image: np.ndarray, brain: np.ndarray, pixel_mm: float) -> dict[str, Callable[[], np.ndarray]]:
    """The changed images, by name: in-plane rings around the manual mask (``pixel_mm`` its pixels)."""
    ring = ndimage.binary_dilation(brain, _in_plane(max(1, int(RING_MM / pixel_mm)))) & ~brain
    far = ~ndimage.binary_dilation(brain, _in_plane(max(1, int(FAR_MM / pixel_mm))))
    bright = float(np.percentile(image, 99.5)) * 0.9

    def changed(where: np.ndarray, value: float | None = None, factor: float = 1.0) -> Callable[[], np.ndarray]:
        def make() -> np.ndarray:
            out = image.copy()
            out[where] = value if value is not None else out[where] * factor
            return out
        return make

    return {"as it is": lambda: image, "a fluid ring of ~4 mm around the brain": changed(ring, bright),
            "everything ~8 mm beyond the brain blanked": changed(far, 0.0),
            "everything ~8 mm beyond the brain bright": changed(far, bright),
            "the brain x0.6": changed(brain, factor=0.6), "the brain x1.4": changed(brain, factor=1.4),
            "the surroundings x0.5": changed(~brain, factor=0.5), "the surroundings x2": changed(~brain, factor=2.0)}


def _in_plane(radius: int) -> np.ndarray:
    """A square in-plane structuring element of ``radius`` pixels (the slice axis is the last)."""
    return np.ones((2 * radius + 1, 2 * radius + 1, 1), bool)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, default=DEFAULT_LOCALISERS_DIR / "default" / "model.onnx")
    ap.add_argument("--stack", type=Path, default=REAL_SCANS / "mial_lausanne_t30" / "sagittal1_lr.nii.gz")
    ap.add_argument("--mask", type=Path, default=None, help="default: <stack>_brain_mask.nii.gz")
    args = ap.parse_args()
    mask_path = args.mask or args.stack.with_name(args.stack.name.replace(".nii.gz", "_brain_mask.nii.gz"))
    if not args.stack.exists() or not mask_path.exists():
        sys.exit(f"needs {args.stack} and {mask_path}")
    vol = read_volume(args.stack)
    if slice_axis_of(vol.spacing) != 2:
        sys.exit("the probes assume slices along the array's last axis")
    brain = read_volume(mask_path).array > 0
    loc = Localiser.load(args.model)
    found = loc.localise(vol).mask
    per_slice = (brain & found).sum((0, 1)) / np.maximum(brain.sum((0, 1)), 1)
    worst = np.sort(np.argsort(np.where(brain.any((0, 1)), per_slice, 2.0))[:8])   # the slices missed most
    print(f"localiser {loc.version}; stack {args.stack.name}; recall shown for slices {worst.tolist()}")
    for name, make in probes(vol.array.astype(np.float32), brain, float(vol.spacing[0])).items():
        mask = loc.localise(Volume(make(), vol.affine)).mask
        recall = (brain & mask).sum((0, 1))[worst] / np.maximum(brain.sum((0, 1))[worst], 1)
        print(f"{name:42s} Dice {dice(mask, brain):.3f}  recall {np.round(recall, 2).tolist()}")


if __name__ == "__main__":
    main()
