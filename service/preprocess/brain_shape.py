"""The brain in a localiser's probability maps: the stack's geometry settles what the network saw.

A fetal head is one convex object: its cross-sections grow from one cap to the widest slice and shrink
to the other, each slice much like its neighbours. What the network takes for brain beyond that is
cut away, on the network's grid of per-slice maps ``[n, H, W]``:

1. the 3D connected component with most probability, weighed by how plausible its volume is for 20-40
   weeks (:func:`plausibility`); a slice in which the network sees (almost) no brain between two of
   that brain's slices is left out and its neighbours joined (:func:`missing_slices`: a slice a signal
   void darkened), as a blank slice is;
2. what hangs on to it through a waist: a thin bridge of one or more slices into the fetal neck, body
   or face, or a dip past which the component widens again (:func:`cut_at_waists`);
3. what a slice adds in its own plane (:mod:`~service.preprocess.slice_trims`) beyond its neighbours
   (``trim_outlier_slices``: a sagittal slice that runs on from the head into the fetal trunk),
   beyond its neighbour nearer the brain's middle where it is wider than that neighbour
   (``trim_growing_caps``: the face beside the frontal lobes in the last slices of a coronal stack)
   or beyond the ellipse its outline follows
   (:func:`~service.preprocess.head_ellipses.trim_to_head_ellipses`: neighbouring slices that run on
   together);
4. its in-plane holes filled (:func:`fill_holes_in_plane`).

Example (a brain of 6 slices whose slice 3 also holds a blob beside the head: the blob is trimmed):
    >>> p = np.zeros((8, 30, 30), np.float32); p[1:7, 4:14, 4:14] = 0.9; p[3, 4:14, 14:28] = 0.8
    >>> brain, _ = brain_from_probabilities(p, voxel_ml=0.01, grid_mm=2.5)
    >>> brain.reshape(8, -1).sum(1).tolist()
    [0, 100, 100, 120, 100, 100, 100, 0]
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from service.preprocess.head_ellipses import trim_to_head_ellipses
from service.preprocess.slice_trims import CAP_GROWTH, trim_growing_caps, trim_outlier_slices
from service.preprocess.stack import mask_box

PLAUSIBLE_ML = (30.0, 700.0)
"""Intracranial volumes of 20-40 weeks' gestation (brain and extra-axial CSF), with a margin."""
MIN_BRAIN_ML = 5.0
THRESHOLD = 0.5
"""The probability above which a pixel of the network's grid is brain for the geometry (one connected
brain, its waists and slices)."""
MASK_THRESHOLD = 0.4
"""The probability above which a pixel of the stack's own grid is in the mask, within the brain the
geometry kept (:meth:`~service.preprocess.localise.Localiser.settle`): the network's probability
falls through the skull's inner edge, and manual masks of the two real scans are drawn at or a little
past that edge (docs/reports/localiser-experiments.md)."""
WAIST_SHARE = 0.15
"""A slice of the brain's component whose area is under this share of the component's largest slice
on each side of it is a waist: a thin bridge into a neighbouring structure (:func:`cut_at_waists`)."""
WAIST_OVERLAP = 0.5
"""A thin slice is a waist only where the slices on either side of it overlap by less than this share
of the smaller: a brain's poor slice lies between two slices of one brain, a bridge between two objects."""
VALLEY_SHARE = 0.3
"""Two or more neighbouring slices, each under this share of the component's largest slice on each side,
are a bridge whatever their overlap, cut at its narrowest slice: a poor slice of a brain comes alone
(its neighbours are acquired at other times), a run of small slices between two large parts joins two
objects (the fetal neck; the face below the brain)."""
END_DIP = 0.5
"""At either end of a component, a run of small slices (each under :data:`VALLEY_SHARE` of the largest)
is a bridge to something else where its narrowest slice is under this share of a slice beyond it: a
brain's cap narrows to its last slice, bits of a fetal body beyond it do not (:func:`end_dips`)."""
MISSING_RUN = 2
"""Up to this many neighbouring slices in which the network sees (almost) no brain between two
slices of one brain are missing slices (:func:`missing_slices`): neighbouring slices of an
interleaved stack are acquired apart in time, and each can be darkened on its own; a head turned in
the picture's plane shows the network a poor slice more often."""
TAIL_SHARE = 0.35
"""What lies beyond a waist is cut off when it holds less than this share of the component's
probability mass; a larger part on each side is the brain itself, split by a poor slice."""


def plausibility(volume_ml: float | NDArray) -> float | NDArray:
    """1 inside :data:`PLAUSIBLE_ML`, falling off linearly in log-volume to 0 at a factor of 3 outside
    (element-wise for an array).

    Example:
        >>> plausibility(300.0), plausibility(10.0), round(plausibility(2100.0), 2)
        (1.0, 0.0, 0.0)
    """
    lo, hi = PLAUSIBLE_ML
    v = np.maximum(np.asarray(volume_ml, np.float64), 1e-9)
    out = np.clip(1.0 - np.maximum(np.maximum(np.log(lo / v), np.log(v / hi)), 0.0) / np.log(3.0), 0.0, 1.0)
    return float(out) if out.ndim == 0 else out


_IN_PLANE = np.zeros((3, 3, 3), bool)
_IN_PLANE[1] = ndimage.generate_binary_structure(2, 1)


def fill_holes_in_plane(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Each slice ``mask[k]`` with its 2D holes filled, in one pass over the mask's bounding box: an
    in-plane structuring element on the box padded by an empty slice at each end (so the end slices'
    faces are not taken for the outside).

    Example (a ring in the middle slice is filled; the column through all three slices is no hole):
        >>> m = np.zeros((3, 7, 7), bool); m[1, 1:6, 1:6] = True; m[1, 3, 3] = False; m[:, 5, 5] = True
        >>> out = fill_holes_in_plane(m)
        >>> bool(out[1, 3, 3]), int(out.sum() - m.sum())
        (True, 1)
    """
    found = np.argwhere(mask)
    if len(found) == 0:
        return np.zeros(mask.shape, bool)
    lo, hi = found.min(0), found.max(0) + 1
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    padded = np.pad(mask[box], ((1, 1), (1, 1), (1, 1)))
    out = np.zeros(mask.shape, bool)
    out[box] = ndimage.binary_fill_holes(padded, structure=_IN_PLANE)[1:-1, 1:-1, 1:-1]
    return out


def cut_at_waists(component: NDArray[np.bool_], prob: NDArray[np.float32]) -> NDArray[np.bool_]:
    """A 3D component of per-slice maps ``[n, H, W]`` without what hangs on to it through a waist.

    A brain's area grows from one cap to its widest slice and shrinks to the other cap. A component
    whose area falls, at some slice, under :data:`WAIST_SHARE` of its largest slice on each side holds
    two objects joined by a thin bridge (the brain leaking into the fetal neck and body, or into the
    amniotic fluid, across one slice), where the slices on either side of it do not overlap
    (:data:`WAIST_OVERLAP`; a poor slice of a brain lies between two overlapping ones) or what lies
    beyond it widens again (:func:`widens_beyond`: a face beyond the skull base), or at the
    narrowest of two or more neighbouring small slices (:data:`VALLEY_SHARE`: a longer bridge), or
    at the narrowest of the small slices at an end where wider ones follow (:func:`end_dips`). The part
    with most probability mass between waists is the brain; everything beyond a waist on either
    side, the waist included, is cut off when it holds under :data:`TAIL_SHARE` of the mass (a poor
    slice through the middle of a brain leaves two large parts and cuts nothing). What stays is the
    largest-mass 3D component of the rest.

    Example (a brain of 6 slices, a 2-pixel bridge, then a 3-slice blob beside it: the blob is cut off):
        >>> c = np.zeros((10, 12, 12), bool); c[0:6, 1:7, 1:7] = True; c[6, 6, 6:8] = True; c[7:10, 6:11, 6:11] = True
        >>> out = cut_at_waists(c, np.where(c, 0.9, 0.0).astype(np.float32))
        >>> out.reshape(10, -1).sum(1).tolist()
        [36, 36, 36, 36, 36, 36, 0, 0, 0, 0]
    """
    area = component.reshape(len(component), -1).sum(1)
    mass = np.where(component, prob, 0.0).reshape(len(component), -1).sum(1)
    rows = np.nonzero(area)[0]
    if len(rows) < 3:
        return component
    lo, hi = rows[0], rows[-1]
    before = np.maximum.accumulate(area[lo:hi + 1])
    after = np.maximum.accumulate(area[lo:hi + 1][::-1])[::-1]
    inner = np.arange(lo + 1, hi)
    largest = np.minimum(before[inner - lo - 1], after[inner - lo + 1])      # on each side
    thin = inner[area[inner] < WAIST_SHARE * largest]
    across = np.array([(component[k - 1] & component[k + 1]).sum() for k in thin])
    waists = thin[across < WAIST_OVERLAP * np.maximum(np.minimum(area[thin - 1], area[thin + 1]), 1)]
    rising = thin[np.array([widens_beyond(k, area, mass) for k in thin], bool)]
    waists = np.union1d(waists, narrowest_of_runs(rising, area, 1))
    waists = np.union1d(waists, narrowest_of_runs(inner[area[inner] < VALLEY_SHARE * largest], area, 2))
    waists = np.union1d(waists, end_dips(area[lo:hi + 1]) + lo)
    if not len(waists):
        return component
    edges = np.concatenate([[lo - 1], waists, [hi + 1]])
    parts = [(a + 1, b) for a, b in zip(edges[:-1], edges[1:]) if b > a + 1]        # slices between waists
    core = max(parts, key=lambda ab: mass[ab[0]:ab[1]].sum())
    keep_from = core[0] if mass[:core[0]].sum() < TAIL_SHARE * mass.sum() else 0
    keep_to = core[1] if mass[core[1]:].sum() < TAIL_SHARE * mass.sum() else len(component)
    if (keep_from, keep_to) == (0, len(component)):
        return component
    kept = np.zeros_like(component)
    kept[keep_from:keep_to] = component[keep_from:keep_to]
    return largest_mass(kept, prob)


def widens_beyond(k: int, area: NDArray, mass: NDArray) -> bool:
    """Whether, beyond slice ``k`` (on the side with less ``mass``), some slice is over
    :data:`~service.preprocess.slice_trims.CAP_GROWTH` times as wide as the wider of the two slices
    past ``k`` on the other side: the profile of ``area`` rises again past ``k``, which no cap of a
    brain does.

    Example (a face of three slices, 22-37 pixels, beyond a thin slice, then a skull base of 16 and
    25 pixels; the same with the face at most 12 pixels wide):
        >>> area = np.array([36, 22, 37, 3, 16, 25, 40, 50, 55, 50, 40, 30])
        >>> bool(widens_beyond(3, area, area)), bool(widens_beyond(3, np.minimum(area, 12), np.minimum(area, 12)))
        (True, False)
    """
    before, after = float(mass[:k].sum()), float(mass[k + 1:].sum())
    beyond, other = (area[:k], area[k + 1:k + 3]) if before < after else (area[k + 1:], area[max(k - 2, 0):k])
    return bool(len(beyond)) and float(beyond.max()) > CAP_GROWTH * float(other.max())


def narrowest_of_runs(small: NDArray, area: NDArray, min_run: int) -> NDArray[np.int64]:
    """The narrowest slice (the first of equals) of each run of ``min_run`` or more neighbours in
    ``small`` (sorted slice indices; ``area`` per slice): where a bridge of small slices is thinnest.

    Example:
        >>> small, area = np.array([3, 6, 7, 8, 11, 12]), np.array([9, 9, 9, 5, 9, 9, 4, 2, 3, 9, 9, 6, 7, 9])
        >>> narrowest_of_runs(small, area, 2).tolist(), narrowest_of_runs(small, area, 1).tolist()
        ([7, 11], [3, 7, 11])
    """
    small = np.asarray(small, np.int64)
    if not len(small):
        return small
    runs = np.split(small, np.flatnonzero(np.diff(small) > 1) + 1)
    return np.array([r[np.argmin(area[r])] for r in runs if len(r) >= min_run], np.int64)


def end_dips(area: NDArray) -> NDArray[np.int64]:
    """Slices (indices into ``area``, one component's area per slice from its first slice to its last)
    where a small end run dips: at each end, the run of slices under :data:`VALLEY_SHARE` of the
    largest slice, when two or more slices lie beyond its narrowest slice (towards the end) and one
    of them is over 1 / :data:`END_DIP` times as wide. A cap that narrows to its last slice has no
    dip, nor one whose last slice alone is wider than a poor slice before it.

    Example (a brain whose last slices are 5, 2, 5, 4 pixels: the dip at 2 is a bridge; its first
    slices, 3 and 8 pixels, are no run of small slices):
        >>> end_dips(np.array([3, 8, 20, 20, 20, 5, 2, 5, 4])).tolist()
        [6]
    """
    area = np.asarray(area, np.float64)
    if not len(area):
        return np.zeros(0, np.int64)
    small = area < VALLEY_SHARE * area.max()
    dips = []
    for order in (np.arange(len(area)), np.arange(len(area))[::-1]):     # towards the last, the first
        inner = np.flatnonzero(~small[order])
        if not len(inner):
            continue
        run = order[inner[-1] + 1:]
        if len(run) < 2:
            continue
        k = int(np.argmin(area[run]))
        if len(run) - k > 2 and area[run[k]] < END_DIP * area[run[k + 1:]].max():
            dips.append(int(run[k]))
    return np.array(sorted(dips), np.int64)


def largest_mass(mask: NDArray[np.bool_], prob: NDArray[np.float32]) -> NDArray[np.bool_]:
    """The 3D connected component of ``mask`` with most probability mass."""
    labels, n = ndimage.label(mask, structure=np.ones((3, 3, 3), bool))
    if n <= 1:
        return mask
    return labels == int(np.argmax(ndimage.sum_labels(prob, labels, np.arange(1, n + 1)))) + 1


def missing_slices(labels: NDArray[np.int32], best: int) -> NDArray[np.bool_]:
    """Slices (of 3D-labelled per-slice maps ``labels [n, H, W]``) in which the network sees (almost) no
    brain between two slices of one brain: up to :data:`MISSING_RUN` neighbouring slices, each under
    :data:`WAIST_SHARE` of the slices on either side of them, which are wide (over
    :data:`VALLEY_SHARE` of the widest slice) and overlap by :data:`WAIST_OVERLAP` of the larger:
    inside component ``best``, or past either end of ``best``'s wide slices, where the slice beyond
    holds another component that so overlaps the last wide slice and is a brain's part (over
    :data:`TAIL_SHARE` of ``best``'s voxels, or over :data:`MISSING_RUN` slices long): one brain that
    slices without it split in two.

    A slice that a signal void or intra-slice motion darkened over the brain shows the network little
    or no brain there: the brain's component ends at it, or the rules that follow take the next slice
    for a growing cap and trim every slice beyond. The two halves lie one above the other, as a
    head's neighbouring slices do; a bridge into the neck, the body or the face does not, and a blob
    of a slice or two past a brain's end is no part of it.

    Example (a brain of 7 slices whose slice 3 the network does not see; then slices 3 and 4):
        >>> p = np.zeros((7, 10, 10), np.float32); p[:, 2:8, 2:8] = 0.9; p[3] = 0.0
        >>> labels, _ = ndimage.label(p > 0.5, structure=np.ones((3, 3, 3), bool))
        >>> missing_slices(labels, 1).tolist()
        [False, False, False, True, False, False, False]
        >>> p[4] = 0.0; labels, _ = ndimage.label(p > 0.5, structure=np.ones((3, 3, 3), bool))
        >>> missing_slices(labels, 1).tolist()
        [False, False, False, True, True, False, False]
    """
    comp = labels == best
    area = comp.reshape(len(comp), -1).sum(1)
    rows = np.flatnonzero(area)
    out = np.zeros(len(labels), bool)
    for run in range(1, MISSING_RUN + 1):                           # poor slices inside the component
        for k in range(rows[0] + 1, rows[-1] - run + 1):
            smaller, larger = sorted((area[k - 1], area[k + run]))
            if smaller >= VALLEY_SHARE * area.max() and np.all(area[k:k + run] < WAIST_SHARE * smaller):
                out[k:k + run] |= (comp[k - 1] & comp[k + run]).sum() >= WAIST_OVERLAP * larger
    wide = np.flatnonzero(area >= VALLEY_SHARE * area.max())
    for last, step in ((wide[-1], 1), (wide[0], -1)):               # past the wide slices at either end
        here = comp[last]
        for run in range(1, MISSING_RUN + 1):
            gap = last + step * np.arange(1, run + 1)
            beyond = last + step * (run + 1)
            if not 0 <= beyond < len(labels):
                break
            if np.any(area[gap] >= WAIST_SHARE * here.sum()) or \
                    any((labels[k] > 0)[here].sum() >= WAIST_SHARE * here.sum() for k in gap):
                break                                               # the brain goes on: no gap
            if area[beyond]:
                break                                               # the component itself goes on
            for other in set(np.unique(labels[beyond][here]).tolist()) - {0, best}:
                there = labels[beyond] == other
                part = labels == other
                brainlike = (np.count_nonzero(part) >= TAIL_SHARE * area.sum()
                             or np.count_nonzero(part.reshape(len(part), -1).any(1)) > MISSING_RUN)
                joined = (there.sum() >= VALLEY_SHARE * area.max() and brainlike
                          and (here & there).sum() >= WAIST_OVERLAP * max(here.sum(), there.sum()))
                out[gap] |= joined
    return out


def brain_from_probabilities(prob: NDArray[np.float32], voxel_ml: float, grid_mm: float = 2.5,
                             blank: NDArray[np.bool_] | None = None, prefer: NDArray[np.bool_] | None = None,
                             ) -> tuple[NDArray[np.bool_], float]:
    """The brain's 3D component in per-slice probability maps ``[n, H, W]`` (``voxel_ml`` the volume of
    one grid voxel, ``grid_mm`` its in-plane size) and the confidence in it.

    ``blank`` marks slices that hold no image (:func:`~service.preprocess.stack.blank_slices`): the
    brain is found as if they were not there, the slices on either side next to each other, and none
    of them is brain. A zero-filled slice would otherwise cut the brain in two, and the geometry keep
    one half. ``prefer`` (the grid's pixels where the request's fetus is,
    :mod:`~service.preprocess.one_fetus`): only the components that reach into it compete.

    Example (two blobs: the larger, surer one wins; the small one is dropped):
        >>> p = np.zeros((6, 20, 20), np.float32); p[1:5, 2:10, 2:10] = 0.95; p[2:3, 15:18, 15:18] = 0.6
        >>> brain, conf = brain_from_probabilities(p, voxel_ml=1.0)
        >>> int(brain.sum()), bool(brain[2, 16, 16]), round(conf, 2)
        (256, False, 0.93)
        >>> p[3] = 0.0                                  # a blank slice in the middle: the brain is joined across it
        >>> [int(b.sum()) for b in brain_from_probabilities(p, 1.0, blank=np.arange(6) == 3)[0]]
        [0, 64, 64, 0, 64, 0]
    """
    if blank is not None and np.any(blank) and not np.all(blank):
        out = np.zeros(prob.shape, bool)
        out[~blank], confidence = brain_from_probabilities(prob[~blank], voxel_ml, grid_mm,
                                                           prefer=None if prefer is None else prefer[~blank])
        return out, confidence
    out = np.zeros(prob.shape, bool)
    above = prob >= THRESHOLD
    box = mask_box(above, [0, 0, 0])                          # every component lies inside it
    if box is None:
        return out, 0.0
    p = prob[box]
    labels, n = ndimage.label(above[box], structure=np.ones((3, 3, 3), bool))
    mass = np.bincount(labels.ravel(), weights=p.ravel(), minlength=n + 1)[1:]
    volume_of = np.bincount(labels.ravel(), minlength=n + 1)[1:] * voxel_ml
    score = mass * plausibility(volume_of) + 1e-6 * mass
    if prefer is not None:
        reaching = np.bincount(labels[np.asarray(prefer, bool)[box]], minlength=n + 1)[1:] > 0
        if not reaching.any():
            return out, 0.0
        score = np.where(reaching, score, -1.0)
    best = int(np.argmax(score)) + 1
    gaps = missing_slices(labels, best)
    if gaps.any():                                            # one brain, split by slices it does not show
        missing = np.zeros(len(prob), bool)
        missing[box[0]][gaps] = True
        return brain_from_probabilities(prob, voxel_ml, grid_mm, missing if blank is None else blank | missing, prefer)
    brain = cut_at_waists(labels == best, p)
    brain = trim_to_head_ellipses(trim_growing_caps(trim_outlier_slices(brain, grid_mm), grid_mm), grid_mm)
    brain = fill_holes_in_plane(largest_mass(brain, p))
    volume_ml = float(brain.sum() * voxel_ml)
    if volume_ml < MIN_BRAIN_ML:
        return out, 0.0
    out[box] = brain
    return out, float(p[brain].mean()) * float(mass[best - 1] / mass.sum()) * plausibility(volume_ml)


