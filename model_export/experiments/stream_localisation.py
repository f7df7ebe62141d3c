"""The localiser slice by slice, as a stream without masks runs it: each slice alone, against each slice
with the maps of its stack's slices received before it.

Slices are sent in an interleaved acquisition order (even slices first); each is localised between its
received neighbours (``service.streaming.arrival.WINDOW`` a side), once alone
(:meth:`~service.preprocess.localise.Localiser.localise_slice`) and once with the maps of the slices
received before it (:meth:`~service.preprocess.localise.Localiser.slice_in_stack`, what a stream
does). Printed per stack (real scans with manual masks: ``NAME.nii.gz`` beside
``NAME_brain_mask.nii.gz``) and for ``--scenes`` held-out whole-uterus scenes of the validation brains
(the generator's own head motion and independent motion per slice): over the slices whose brain
(mask) covers more than :data:`BRAIN_SLICE_MM2`, each slice's Dice (median, mean) and how many
score under 0.5, and the milliseconds a slice.

    .venv/bin/python model_export/experiments/stream_localisation.py ../shared/data/real_scans/mial_lausanne_t30 [DIR/mial_sub01] [--scenes 16]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.acquisitions import interleaved_times  # noqa: E402
from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes, split  # noqa: E402
from model_export.localiser.evaluate import dice, masked_files  # noqa: E402
from model_export.localiser.scenes import HeadModel, synth_scene  # noqa: E402
from service.geometry.pose import translate  # noqa: E402
from service.io.volume import Volume, read_volume  # noqa: E402
from service.preprocess.localise import Localiser, default_localiser  # noqa: E402
from service.preprocess.stack import stack_axis  # noqa: E402
from service.streaming.arrival import WINDOW  # noqa: E402

BRAIN_SLICE_MM2 = 300.0


def streamed(localiser: Localiser, volume: Volume, with_stack: bool) -> tuple[np.ndarray, float]:
    """Each slice's mask ``[H, W, n]`` (the slice axis last), localised in interleaved order as a stream
    does, and the seconds a slice."""
    axis = stack_axis(volume)
    array = np.moveaxis(volume.array, axis, 2)
    affine = volume.affine.copy()
    affine[:3, :3] = volume.affine[:3, :3][:, [a for a in range(3) if a != axis] + [axis]]
    n = array.shape[2]
    received: dict[int, np.ndarray] = {}
    masks = np.zeros(array.shape, bool)
    t = time.perf_counter()
    for k in map(int, np.argsort(interleaved_times(n))):
        lo = hi = k
        while lo - 1 in received and k - lo < WINDOW:
            lo -= 1
        while hi + 1 in received and hi - k < WINDOW:
            hi += 1
        window = Volume(np.ascontiguousarray(array[:, :, lo:hi + 1]), affine @ translate([0.0, 0.0, float(lo)]),
                        slice_axis=2)
        found, received[k] = localiser.slice_in_stack(window, k - lo, received if with_stack else None, k,
                                                    float(volume.spacing[axis]))
        masks[:, :, k] = found.mask[:, :, k - lo]
    return masks, (time.perf_counter() - t) / n


def slice_dice(localiser: Localiser, volume: Volume, truth: np.ndarray) -> dict[bool, tuple[np.ndarray, float]]:
    """Per brain slice, its Dice streamed alone (``False``) and with the stack (``True``), and the seconds a slice."""
    truth = np.moveaxis(truth, stack_axis(volume), 2)
    pixel_mm2 = float(np.prod(np.delete(volume.spacing, stack_axis(volume))))
    brain = np.flatnonzero(truth.reshape(-1, truth.shape[2]).sum(0) * pixel_mm2 > BRAIN_SLICE_MM2)
    out = {}
    for with_stack in (False, True):
        masks, seconds = streamed(localiser, volume, with_stack)
        out[with_stack] = (np.array([dice(masks[:, :, k], truth[:, :, k]) for k in brain]), seconds)
    return out


def report(label: str, rows: list[dict[bool, tuple[np.ndarray, float]]]) -> None:
    """One line each way, over ``rows`` pooled."""
    for with_stack in (False, True):
        d = np.concatenate([r[with_stack][0] for r in rows])
        ms = 1e3 * float(np.mean([r[with_stack][1] for r in rows]))
        print(f"{label} {'with the stack' if with_stack else 'alone':>14}: {len(d)} brain slices, Dice median "
              f"{np.median(d):.3f} mean {d.mean():.3f}, {int((d < 0.5).sum())} under 0.5; {ms:.0f} ms a slice",
              flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scans", type=Path, nargs="*", help="folders of real stacks with manual masks")
    ap.add_argument("--scenes", type=int, default=0, help="held-out whole-uterus scenes per head motion")
    args = ap.parse_args()
    localiser = default_localiser()
    for folder in args.scans:
        for name, stack, mask in masked_files(folder):
            volume = read_volume(stack)
            report(f"{folder.name}/{name}", [slice_dice(localiser, volume, read_volume(mask).array > 0)])
    if args.scenes:
        heads = [HeadModel.from_arrays(v.image, v.mask, v.affine)
                 for v in load_volumes(split(DEFAULT_ATLAS_ROOT)[1], DEFAULT_ATLAS_ROOT)]
        for motion in (None, "independent"):
            scenes = [synth_scene(heads[i % len(heads)], np.random.default_rng(5_000_000 + i), "heldout", motion=motion)
                      for i in range(args.scenes)]
            report(f"{args.scenes} held-out scenes ({motion or 'their own head motion'})",
                   [slice_dice(localiser, s.volume, s.mask) for s in scenes])

if __name__ == "__main__":
    main()
