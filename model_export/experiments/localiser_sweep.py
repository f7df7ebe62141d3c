"""The localiser on real stacks rewritten as other scanners would write them.

Real scans of other sites differ from the ones at hand in their pixel size, field of view, slice
spacing, contrast, noise and shading, and in how their files order and orient the voxels. This
script takes every real stack with a manual mask (``NAME_brain_mask.nii.gz`` beside it, in each
``SCAN`` folder), rewrites stack and mask alike in each way below, localises the stack and prints
the Dice against the rewritten mask, per stack and as the median and minimum per rewrite:

* ``base``: the file as it is;
* ``slice-axis-first``, ``in-plane-swapped``, ``x-reversed``, ``y-reversed``: the same voxels
  stored in another order (the slice axis first; the two in-plane axes swapped; the first or the
  second in-plane axis last to first), the header saying so;
* ``px0.7``, ``px1.6``, ``px2.0``: in-plane pixels of that size (anti-aliased when coarser);
* ``fov250``, ``fov420``: the field of view cut to 250 mm about its centre (where the brain stays
  in it) or widened to 420 mm with background; ``cropped``: cut to the head, the manual mask's
  box and 15 mm (a stack cropped before it is sent, as other pipelines do); ``cropped-tight``:
  cut to the mask's box itself;
* ``gamma0.6``, ``gamma1.6``: another contrast; ``noise``, ``noise15``: Rician noise of 6 % or 15 %
  of the bright end (a low-field scanner's);
  ``shading``: a smooth field over a factor of 3 across the field of view; ``scale1e3``: another
  intensity range;
* ``every2nd``: every other slice (slices twice as far apart);
* ``first-half``, ``last-half``, ``brain-slab``: a stack that covers part of the brain (up to or
  from its middle slice, with what lies beyond its end), or the brain's slices alone;
* ``zero-filled``: the brain's middle slice filled with zeros (a slice a scanner or a QC step
  blanked; its mask is then empty too); ``dark-slice``: that slice at a tenth of its intensity;
  ``signal-void``: half of it (its first columns) at a fifth (a slice that intra-slice motion
  darkened);
* ``wrap-u``, ``wrap-v``: the field of view cut to 70 % along one in-plane axis (a rectangular
  field of view along the phase-encoding direction), what lies beyond it folded back over the
  image (aliasing: the two magnitudes summed as signals of random phase), the brain kept inside;
* ``edge0``, ``edge15``: the field of view ending at the brain's outline along one in-plane axis,
  or 15 mm inside it (a head at the edge of the image; the mask cut alike);
* ``turned15``, ``turned30``, ``turned45``: each slice's content turned by that many degrees in
  its plane about the field of view's centre (a head at another angle to the picture's rows, as a
  stack planned at another in-plane angle shows it);
* ``moving``: each slice's content (and mask) shifted in its plane by up to 10 mm either way (the
  fetus moving between slices);
* ``younger0.8``, ``younger0.7``: the voxels said to be 0.8 or 0.7 times their size (the header
  alone), so that head, uterus and body are that much smaller: a younger pregnancy's scale (the
  shared scan's brain then 180 / 120 ml, `sub-01`'s about 70 / 45 ml, as at 20-23 weeks).

A localiser whose masks hold under every rewrite does not depend on what one scanner writes.
``--single-pass`` runs the network without its mirror-image pass (:attr:`Localiser.mirrored`);
``--grid-mm G`` runs it on a grid of ``G`` mm pixels instead of the one it learnt (fewer pixels to
a stack, a brain that looks smaller); ``--rewrites base,px1.6`` runs only those rewrites.

    .venv/bin/python model_export/experiments/localiser_sweep.py ../shared/data/real_scans/mial_lausanne_t30 [SCAN ...] \\
        [--model M] [--single-pass] [--grid-mm 3.0] [--rewrites base]
"""

from __future__ import annotations

import argparse
import itertools
import sys
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.localiser.evaluate import dice, masked_files  # noqa: E402
from service.geometry.pose import index_reversal  # noqa: E402
from service.io.volume import Volume, read_volume  # noqa: E402
from service.preprocess.localise import Localiser, default_localiser  # noqa: E402
from service.preprocess.stack import slice_axis_of, stack_axis  # noqa: E402

Rewrite = tuple[str, Volume, NDArray[np.bool_]]


def reordered(volume: Volume, mask: NDArray | None, order: tuple[int, int, int]) -> tuple[Volume, NDArray | None]:
    """The same voxels with their axes in ``order``, the affine permuted alike (the world unchanged);
    the mask alike (None: none)."""
    affine = volume.affine.copy()
    affine[:3, :3] = volume.affine[:3, :3][:, list(order)]
    return (Volume(np.ascontiguousarray(volume.array.transpose(order)), affine),
            None if mask is None else mask.transpose(order))


def reversed_axis(volume: Volume, mask: NDArray | None, axis: int) -> tuple[Volume, NDArray | None]:
    """The voxels along ``axis`` stored last to first, the affine saying so (the world unchanged); the
    mask alike (None: none)."""
    affine = volume.affine @ index_reversal(axis, volume.array.shape[axis])
    return (Volume(np.ascontiguousarray(np.flip(volume.array, axis)), affine),
            None if mask is None else np.flip(mask, axis))


STORAGES = list(itertools.product([False, True], repeat=3))
"""Every ``(first, second, swapped)`` of :func:`stored_as`: the eight ways a file can store a stack's
two in-plane voxel axes (the first is the file's own)."""


def stored_as(volume: Volume, first: bool, second: bool, swapped: bool) -> Volume:
    """``volume`` as a file that stores its in-plane voxel axes otherwise holds it: the first and or
    the second reversed, then the two swapped (each voxel where it was in the world). A mask rides
    along as a volume of its own (``stored_as(Volume(mask, affine), ...)``)."""
    axis = stack_axis(volume)
    p, q = (a for a in range(3) if a != axis)
    for along, flip in ((p, first), (q, second)):
        if flip:
            volume = reversed_axis(volume, None, along)[0]
    if swapped:
        order = [0, 1, 2]
        order[p], order[q] = q, p
        volume = reordered(volume, None, tuple(order))[0]
    return volume


def in_plane_pixels(volume: Volume, mask: NDArray, pixel_mm: float) -> tuple[Volume, NDArray]:
    """The stack resampled to square in-plane pixels of ``pixel_mm`` over the same field of view
    (linear; Gaussian anti-aliasing first when coarser), its mask alike (at 0.5)."""
    axis = slice_axis_of(volume.spacing)
    plane = [a for a in range(3) if a != axis]
    shape = np.array(volume.array.shape)
    new = shape.copy()
    new[plane] = np.maximum(np.round(shape[plane] * volume.spacing[plane] / pixel_mm), 2).astype(int)
    step = np.where(new > 1, (shape - 1) / np.maximum(new - 1, 1), 1.0)   # old voxels per new voxel
    image = volume.array.astype(np.float32)
    sigma = [0.4 * s if a in plane and s > 1 else 0.0 for a, s in enumerate(step)]
    if any(sigma):
        image = ndimage.gaussian_filter(image, sigma)
    coords = np.meshgrid(*[np.arange(n) * s for n, s in zip(new, step)], indexing="ij")
    image = ndimage.map_coordinates(image, coords, order=1)
    resampled = ndimage.map_coordinates(mask.astype(np.float32), coords, order=1) >= 0.5
    affine = volume.affine.copy()
    affine[:3, :3] = volume.affine[:3, :3] * step
    return Volume(image.astype(np.float32), affine), resampled


def turned_in_plane(volume: Volume, mask: NDArray, degrees: float) -> tuple[Volume, NDArray]:
    """The stack's content turned by ``degrees`` in the plane of its slices about the field of
    view's centre (in mm: pixels need not be square), stack and mask alike (linear, the mask at 0.5):
    a head lying at another angle to the picture's rows, as a stack planned at another in-plane
    angle shows it. What turns out of the picture is lost; what turns in is the background."""
    axis = slice_axis_of(volume.spacing)
    plane = [a for a in range(3) if a != axis]
    shape = np.array(volume.array.shape)
    spacing = np.asarray(volume.spacing, np.float64)
    grid = np.meshgrid(*[np.arange(n, dtype=np.float64) for n in shape], indexing="ij")
    mm = [(grid[a] - (shape[a] - 1) / 2.0) * spacing[a] for a in plane]
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    source = list(grid)                                   # each output voxel's place in the input
    source[plane[0]] = (c * mm[0] + s * mm[1]) / spacing[plane[0]] + (shape[plane[0]] - 1) / 2.0
    source[plane[1]] = (-s * mm[0] + c * mm[1]) / spacing[plane[1]] + (shape[plane[1]] - 1) / 2.0
    image = volume.array.astype(np.float32)
    background = float(np.percentile(image, 5))
    turned = ndimage.map_coordinates(image, source, order=1, cval=background)
    turned_mask = ndimage.map_coordinates(mask.astype(np.float32), source, order=1, cval=0.0) >= 0.5
    return Volume(turned.astype(np.float32), volume.affine), turned_mask


def wrapped(volume: Volume, mask: NDArray, axis: int, share: float) -> tuple[Volume, NDArray] | None:
    """The stack acquired with ``share`` of its field of view along ``axis`` (about the image's
    centre, moved as little as keeps the brain inside), what lies beyond folded back over it: the
    magnitudes of the pixels that land on one pixel combine as signals of random phase (``hypot``).
    None where the brain does not fit."""
    n = volume.array.shape[axis]
    m = int(round(share * n))
    inside = np.flatnonzero(np.moveaxis(mask, axis, 0).reshape(n, -1).any(axis=1))
    if not len(inside) or inside[-1] - inside[0] + 1 > m:
        return None
    start = int(np.clip((n - m) // 2, inside[-1] + 1 - m, inside[0]))
    image = np.moveaxis(volume.array.astype(np.float64), axis, 0)
    folded = np.zeros((m, *image.shape[1:]))
    for i in range(n):
        folded[(i - start) % m] += image[i] ** 2
    box = [slice(None)] * 3
    box[axis] = slice(start, start + m)
    return (Volume(np.moveaxis(np.sqrt(folded), 0, axis).astype(np.float32), volume.region(tuple(box)).affine),
            mask[tuple(box)])


def rewrites(volume: Volume, mask: NDArray[np.bool_], rng: np.random.Generator) -> Iterator[Rewrite]:
    """Every rewrite of the module's list, stack and mask alike."""
    yield "base", volume, mask
    axis = slice_axis_of(volume.spacing)
    yield ("slice-axis-first", *reordered(volume, mask, (axis, *[a for a in range(3) if a != axis])))
    plane = [a for a in range(3) if a != axis]
    swapped = [0, 1, 2]
    swapped[plane[0]], swapped[plane[1]] = plane[1], plane[0]
    yield ("in-plane-swapped", *reordered(volume, mask, tuple(swapped)))
    yield ("x-reversed", *reversed_axis(volume, mask, plane[0]))
    yield ("y-reversed", *reversed_axis(volume, mask, plane[1]))
    for pixel_mm in (0.7, 1.6, 2.0):
        yield (f"px{pixel_mm}", *in_plane_pixels(volume, mask, pixel_mm))
    image = volume.array.astype(np.float32)
    box = [slice(None)] * 3
    for a in plane:
        n = int(round(250 / volume.spacing[a]))
        start = max(0, (image.shape[a] - n) // 2)
        box[a] = slice(start, start + n)
    if mask[tuple(box)].sum() > 0.95 * mask.sum():
        yield "fov250", volume.region(tuple(box)), mask[tuple(box)]
    found = np.argwhere(mask)
    for name, margin_mm in (("cropped", 15), ("cropped-tight", 0)) if len(found) else ():
        head = [slice(None)] * 3
        for a in plane:
            margin = int(round(margin_mm / volume.spacing[a]))
            head[a] = slice(max(0, found[:, a].min() - margin), found[:, a].max() + 1 + margin)
        yield name, volume.region(tuple(head)), mask[tuple(head)]
    pad = [(0, 0)] * 3
    for a in plane:
        p = max(0, int(round((420 / volume.spacing[a] - image.shape[a]) / 2)))
        pad[a] = (p, p)
    affine = volume.affine.copy()
    affine[:3, 3] -= affine[:3, :3] @ [p for p, _ in pad]
    yield ("fov420", Volume(np.pad(image, pad, constant_values=float(np.percentile(image, 5))), affine),
           np.pad(mask, pad))
    bright = float(np.percentile(image, 99.5))
    for gamma in (0.6, 1.6):
        yield f"gamma{gamma}", Volume(bright * (np.clip(image, 0, None) / bright) ** gamma, volume.affine), mask
    own = np.random.default_rng(1)                  # the rewrites added later draw apart from ``rng``
    for name, share, draws in (("noise", 0.06, rng), ("noise15", 0.15, own)):
        s = share * bright
        yield name, Volume(np.hypot(image + draws.normal(0, s, image.shape), draws.normal(0, s, image.shape))
                           .astype(np.float32), volume.affine), mask
    u, v = np.meshgrid(*[np.linspace(-1, 1, image.shape[a]) for a in plane], indexing="ij")
    field = np.expand_dims(np.exp(np.log(3.0) / 2 * (u + 0.5 * v) / 1.5), axis)
    yield "shading", Volume(image * field, volume.affine), mask
    yield "scale1e3", Volume(image * (1000.0 / bright), volume.affine), mask
    keep = [slice(None)] * 3
    keep[axis] = slice(None, None, 2)
    doubled = np.eye(4)
    doubled[axis, axis] = 2.0
    yield "every2nd", Volume(np.ascontiguousarray(image[tuple(keep)]), volume.affine @ doubled), mask[tuple(keep)]
    brain = np.flatnonzero(np.moveaxis(mask, axis, 0).reshape(mask.shape[axis], -1).any(axis=1))
    if len(brain):
        middle = (brain[0] + brain[-1] + 1) // 2
        for name, part in (("first-half", slice(0, middle)), ("last-half", slice(middle, mask.shape[axis])),
                           ("brain-slab", slice(brain[0], brain[-1] + 1))):
            box = [slice(None)] * 3
            box[axis] = part
            yield name, volume.region(tuple(box)), mask[tuple(box)]
        box = [slice(None)] * 3
        box[axis] = slice(middle, middle + 1)
        blanked, unseen = image.copy(), mask.copy()
        blanked[tuple(box)], unseen[tuple(box)] = 0.0, False
        yield "zero-filled", Volume(blanked, volume.affine), unseen
        dark, void = image.copy(), np.moveaxis(image.copy(), axis, 0)
        dark[tuple(box)] *= 0.1
        void[middle, :, : void.shape[2] // 2] *= 0.2
        yield "dark-slice", Volume(dark, volume.affine), mask
        yield "signal-void", Volume(np.ascontiguousarray(np.moveaxis(void, 0, axis)), volume.affine), mask
    for name, a in (("wrap-u", plane[0]), ("wrap-v", plane[1])):
        folded = wrapped(volume, mask, a, 0.7)
        if folded is not None:
            yield (name, *folded)
    if len(found):
        a = plane[0]
        for cut_mm in (0, 15):
            box = [slice(None)] * 3
            box[a] = slice(found[:, a].min() + int(round(cut_mm / volume.spacing[a])), None)
            yield f"edge{cut_mm}", volume.region(tuple(box)), mask[tuple(box)]
    for degrees in (15, 30, 45):
        yield (f"turned{degrees}", *turned_in_plane(volume, mask, degrees))
    moved, moved_mask = np.moveaxis(image.copy(), axis, 0), np.moveaxis(mask.copy(), axis, 0)
    for k in range(len(moved)):
        shift = own.uniform(-10.0, 10.0, 2) / volume.spacing[plane]
        moved[k] = ndimage.shift(moved[k], shift, order=1)
        moved_mask[k] = ndimage.shift(moved_mask[k].astype(np.float32), shift, order=1) >= 0.5
    yield "moving", Volume(np.ascontiguousarray(np.moveaxis(moved, 0, axis)), volume.affine), np.moveaxis(moved_mask, 0, axis)
    for scale in (0.8, 0.7):
        smaller = volume.affine.copy()
        smaller[:3, :3] *= scale
        yield f"younger{scale}", Volume(image, smaller), mask


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scans", type=Path, nargs="+", help="real scan folders with manual masks")
    ap.add_argument("--model", type=Path, help="a localiser ONNX file (default: the shipped one)")
    ap.add_argument("--single-pass", action="store_true", help="without the mirror-image pass")
    ap.add_argument("--grid-mm", type=float, help="the network's grid (default: the one it learnt)")
    ap.add_argument("--rewrites", help="only these rewrites, comma-separated (default: all)")
    args = ap.parse_args()
    localiser = Localiser.load(args.model) if args.model else default_localiser()
    localiser.mirrored = not args.single_pass
    if args.grid_mm:
        localiser.grid_mm = args.grid_mm
    chosen = None if args.rewrites is None else set(args.rewrites.split(","))
    rng = np.random.default_rng(0)
    scores: dict[str, list[float]] = defaultdict(list)
    for scan in args.scans:
        files = masked_files(scan)
        if not files:
            sys.exit(f"no stack with a manual mask in {scan}")
        for name, stack, mask_file in files:
            volume, mask = read_volume(stack), read_volume(mask_file).array > 0
            row = []
            for rewrite, v, m in rewrites(volume, mask, rng):
                if chosen is not None and rewrite not in chosen:
                    continue
                found = localiser.localise(v)
                scores[rewrite].append(dice(found.mask, m))
                row.append(f"{rewrite} {scores[rewrite][-1]:.3f}")
            print(f"{scan.name}/{name}: " + ", ".join(row), flush=True)
    print(f"\n{'rewrite':18s} median   min  (Dice over {len(next(iter(scores.values())))} stacks; "
          f"{'one pass' if args.single_pass else 'with the mirror-image pass'})")
    for rewrite, d in scores.items():
        print(f"{rewrite:18s} {np.median(d):.3f} {min(d):.3f}")
    every = np.concatenate([d for d in scores.values()])
    print(f"{'all rewrites':18s} {np.median(every):.3f} {every.min():.3f}")


if __name__ == "__main__":
    main()
