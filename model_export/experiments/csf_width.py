"""Does the localiser follow the skull, or a CSF layer of the width it was trained on?

Generated whole-uterus scenes of the validation brains (held-out style, T2-like contrast), each drawn
again with its extra-axial CSF layer set to each of ``--widths`` (mm; the training scenes draw
1–3.5 mm) and everything else the same; printed per width: the localiser's Dice against the
skull-inside truth and its found / true volume (median over the scenes). A localiser that stops at a
fixed distance from the brain loses volume as the layer widens. ``--patches``: the same scenes with
their drawn layer widened in patches by up to each of these (mm; :func:`~model_export.localiser.scenes.csf_patches`),
as a real head's CSF is: wide in places, thin elsewhere; printed beside: the share of the true mask
the localiser misses inside the widened CSF. ``--faint-skull``: every head's skull thin and nearly as bright as
the fluid (``synth_scene(faint_skull_share=1)``: a young fetus's skull on a 1.1 mm grid).

    .venv/bin/python model_export/experiments/csf_width.py [--model M] [--scenes 12] [--widths 1.5,3,5,7] [--patches 4,8] [--faint-skull]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.atlas import DEFAULT_ATLAS_ROOT, VALIDATION_VOLUMES, load_volumes  # noqa: E402
from model_export.localiser.evaluate import dice  # noqa: E402
from model_export.localiser.scenes import HeadModel, synth_scene  # noqa: E402
from service.preprocess.localise import Localiser, default_localiser  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, help="a localiser ONNX file (default: the shipped one)")
    ap.add_argument("--scenes", type=int, default=12)
    ap.add_argument("--widths", default="1.5,3,5,7")
    ap.add_argument("--patches", default="", help="widest CSF patches, mm (comma-separated; 0: none)")
    ap.add_argument("--faint-skull", action="store_true", help="thin skulls of nearly the fluid's intensity")
    args = ap.parse_args()
    if not DEFAULT_ATLAS_ROOT.exists():
        sys.exit(f"needs the atlas volumes at {DEFAULT_ATLAS_ROOT}")
    localiser = Localiser.load(args.model) if args.model else default_localiser()
    heads = [HeadModel.from_arrays(v.image, v.mask, v.affine) for v in load_volumes(list(VALIDATION_VOLUMES))]
    faint = float(args.faint_skull)
    for widest in (float(w) for w in args.patches.split(",") if w):
        d, v, m = measure(localiser, heads, args.scenes, csf_patches_mm=widest, faint_skull_share=faint)
        print(f"CSF patches up to {widest:g} mm: Dice median {np.median(d):.3f} (min {d.min():.3f}); "
              f"found / true volume median {np.median(v):.2f}; CSF missed median {np.median(m):.2f}", flush=True)
    for width in (float(w) for w in args.widths.split(",") if w):
        d, v, _ = measure(localiser, heads, args.scenes, csf_mm=width, faint_skull_share=faint)
        print(f"CSF layer {width:g} mm: Dice median {np.median(d):.3f} (min {d.min():.3f}); "
              f"found / true volume median {np.median(v):.2f}", flush=True)


def measure(localiser: Localiser, heads: list[HeadModel], scenes: int, **drawn: float) -> np.ndarray:
    """``[3, scenes]``: the localiser's Dice, found / true volume and share of the CSF missed on held-out
    scenes (T2-like contrast, seeds 1000...) drawn with ``drawn`` (:func:`synth_scene`'s options)."""
    rows = []
    for seed in range(scenes):
        scene = synth_scene(heads[seed % len(heads)], np.random.default_rng(1000 + seed), "heldout",
                            random_contrast=False, **drawn)
        found = localiser.localise(scene.volume).mask
        csf = scene.mask & ~scene.brain
        rows.append((dice(found, scene.mask), found.sum() / max(scene.mask.sum(), 1),
                     (csf & ~found).sum() / max(csf.sum(), 1)))
    return np.array(rows).T

if __name__ == "__main__":
    main()
