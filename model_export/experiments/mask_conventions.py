"""Where manual masks draw the brain's edge against the localiser's mask, slice by slice.

For every ``<stack>_brain_mask.nii.gz`` beside its ``<stack>.nii.gz`` in the folders given, the
shipped localiser's mask of the stack, its Dice against the manual mask as it is and grown in each
slice's plane by 1-4 mm (:func:`~service.preprocess.localisation.grown` with the slice axis out of
reach), and the signed in-plane distance of the manual outline from the localiser's mask (median
and quartiles; positive: the manual outline lies outside). Two annotators' conventions show as a
constant offset (docs/reports/localiser-experiments.md, "Where the Dice is lost on the real stacks").

    .venv/bin/python model_export/experiments/mask_conventions.py ../shared/data/real_scans/mial_lausanne_t30 DIR/mial_sub01
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy import ndimage

from model_export.localiser.evaluate import dice
from service.io.volume import read_volume
from service.preprocess.localisation import grown
from service.preprocess.localise import default_localiser
from service.preprocess.stack import slice_axis_of

MARGINS_MM = (1.0, 2.0, 3.0, 4.0)


def outline_offsets_mm(manual: np.ndarray, found: np.ndarray, in_plane: np.ndarray) -> np.ndarray:
    """Signed distance (mm, in each slice's plane) of every pixel of the manual outline from the
    boundary of ``found``: positive outside it, negative inside; ``in_plane`` the voxel sizes with the
    slice axis made unreachable."""
    cross = ndimage.generate_binary_structure(3, 1)
    np.moveaxis(cross, int(np.argmax(in_plane)), 0)[[0, 2]] = False     # neighbours in the slice's plane only
    edge = manual & ~ndimage.binary_erosion(manual, structure=cross)
    outside = ndimage.distance_transform_edt(~found, sampling=in_plane)
    inside = ndimage.distance_transform_edt(found, sampling=in_plane)
    return np.where(found[edge], -inside[edge], outside[edge])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+", type=Path)
    args = ap.parse_args()
    localiser = default_localiser()
    print("| stack | Dice as is | grown " + " / ".join(f"{m:g}" for m in MARGINS_MM) + " mm | manual outline from "
          "the localiser's mask: median (quartiles), mm |")
    print("|---|---|---|---|")
    for folder in args.folders:
        for path in sorted(folder.glob("*_brain_mask.nii.gz")):
            stack = read_volume(path.with_name(path.name.replace("_brain_mask", "")))
            manual = read_volume(path).array > 0
            found = localiser.localise(stack).mask
            in_plane = np.array(stack.spacing, np.float64)
            in_plane[slice_axis_of(stack.spacing)] = 1e6
            offsets = outline_offsets_mm(manual, found, in_plane)
            grown_dice = [dice(grown(found, in_plane, m), manual) for m in MARGINS_MM]
            q1, med, q3 = np.percentile(offsets, [25, 50, 75])
            print(f"| {folder.name}/{path.name.replace('_brain_mask.nii.gz', '')} | {dice(found, manual):.3f} | "
                  + " / ".join(f"{d:.3f}" for d in grown_dice) + f" | {med:+.1f} ({q1:+.1f}, {q3:+.1f}) |")


if __name__ == "__main__":
    main()
