"""One fetus per request: the brain the localiser settles on in every stack is the same fetus's.

A twin pregnancy puts two heads in a whole-uterus field of view. Each stack's geometry keeps the
brain of most (plausible) probability, and stacks of one request can settle on different heads:
their poses then describe two brains. The stacks share the scanner's frame, so where a brain lies
is comparable across them. Where the stacks' brains lie farther apart than a fetus moves between
stacks (:data:`BRAIN_MOVE_MM`), the request's fetus is the place most of them agree on (weighed by
their confidence; an uploaded mask's brain, the user's choice, decides alone), and every stack that
settled elsewhere settles again on the brain it saw there (or keeps its own where it saw none there).

Example (stacks settled 100 mm apart: two of three agree; an uploaded mask's brain decides alone):
    >>> centres = [np.array([0.0, 0.0, 0.0]), np.array([100.0, 0.0, 0.0]), np.array([95.0, 10.0, 0.0])]
    >>> request_centre(centres, [0.9, 0.5, 0.5], fixed=[]).tolist()
    [100.0, 0.0, 0.0]
    >>> request_centre(centres, [0.9, 0.5, 0.5], fixed=[np.array([3.0, 5.0, 0.0])]).tolist()
    [3.0, 5.0, 0.0]
    >>> request_centre(centres[1:], [0.5, 0.5], fixed=[]) is None                 # one fetus
    True
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from service.io.volume import Volume
from service.preprocess.localiser_inputs import LocaliserGrid, target_maps


class Settled(Protocol):
    """What :func:`one_fetus` reads of a stack's localisation
    (:class:`~service.preprocess.localisation.Localisation`)."""

    mask: NDArray
    confidence: float
    brain_volume_ml: float


class Settles(Protocol):
    """What :func:`one_fetus` asks of a localiser (:class:`~service.preprocess.localise.Localiser`)."""

    def settle(self, volume: Volume, prob: NDArray, grid: LocaliserGrid, prefer: NDArray | None = None) -> Settled:
        ...

BRAIN_MOVE_MM = 60.0
"""Stacks whose brains' centres lie within this of each other see one fetus (a fetal head moves
tens of millimetres between stacks; two fetuses' heads, side by side, have their centres 75 mm or
more apart)."""
CENTRE_REACH_MM = 20.0
"""A stack's brain is the request's fetus's where it reaches within this of the fetus's centre (a
twin's brain, its centre 75 mm or more away, ends farther from it)."""


def brain_centre_mm(mask: NDArray, affine: NDArray) -> NDArray[np.float64] | None:
    """The centre of a mask's voxels in scanner mm (None for an empty mask), from the mask's counts
    along each axis (no list of its voxels: a fine grid's mask holds millions).

    Example (voxels 1 and 2 along x, 0 along y and z; 2 mm voxels, origin 10 mm along x):
        >>> m = np.zeros((4, 2, 2), bool); m[1:3, 0, 0] = True
        >>> affine = np.diag([2.0, 2.0, 2.0, 1.0]); affine[0, 3] = 10.0
        >>> brain_centre_mm(m, affine).tolist()
        [13.0, 0.0, 0.0]
    """
    m = np.asarray(mask, bool)
    count = np.count_nonzero(m)
    if count == 0:
        return None
    index = [np.arange(m.shape[a]) @ np.count_nonzero(m, axis=tuple(k for k in range(m.ndim) if k != a))
             for a in range(m.ndim)]
    return np.asarray(affine, np.float64)[:3, :3] @ (np.array(index, np.float64) / count) + \
        np.asarray(affine, np.float64)[:3, 3]


def request_centre(centres: list[NDArray | None], confidences: list[float],
                   fixed: list[NDArray]) -> NDArray[np.float64] | None:
    """Where the request's fetus is: None where every brain found (and every uploaded mask's,
    ``fixed``) lies within :data:`BRAIN_MOVE_MM` of the others; otherwise the uploaded masks' first
    brain, or the found brain whose neighbourhood holds the most confidence."""
    found = [(c, w) for c, w in zip(centres, confidences) if c is not None]
    places = [np.asarray(c, np.float64) for c in fixed] + [c for c, _ in found]
    if len(places) < 2 or max(np.linalg.norm(a - b) for a in places for b in places) <= BRAIN_MOVE_MM:
        return None
    if fixed:
        return np.asarray(fixed[0], np.float64)
    support = [sum(w for c, w in found if np.linalg.norm(c - here) <= BRAIN_MOVE_MM) for here, _ in found]
    return np.asarray(found[int(np.argmax(support))][0], np.float64)


def apart_from_fetus(centres: list[NDArray | None], confidences: list[float],
                     uploaded: list[bool] | None = None) -> NDArray[np.float64]:
    """How far each stack's brain lies from the request's fetus, where it lies farther than
    :data:`BRAIN_MOVE_MM`: mm, NaN where it lies with it, sees no brain (``None``), or the request's
    brains are one fetus's. The request's fetus is the user's where the request uploaded masks
    (``uploaded``: which stacks' brains are an uploaded mask's): the place most of those masks'
    brains lie near; otherwise the place most of the brains found lie near, weighed by
    ``confidences`` (:func:`request_centre`). Where the stacks divide evenly between two places,
    the first stack's is the request's.

    The request's later stages (the stacks' branches decided together, their placements pooled,
    their slices refined where they cross) relate the stacks of one fetus. A stack whose mask holds
    another fetus's brain (a twin, or another scan's file) would pull the others towards a brain
    that is not theirs.

    Example (two stacks of one fetus, a third 100 mm away; all three on one fetus; the third's brain
    an uploaded mask's, the others the localiser's):
        >>> centres = [np.zeros(3), np.array([10.0, 0.0, 0.0]), np.array([100.0, 0.0, 0.0])]
        >>> apart_from_fetus(centres, [1.0, 1.0, 1.0]).tolist()
        [nan, nan, 100.0]
        >>> apart_from_fetus(centres[:2] + [None], [1.0, 1.0, 0.0]).tolist()
        [nan, nan, nan]
        >>> apart_from_fetus(centres, [0.9, 0.9, 1.0], uploaded=[False, False, True]).round(1).tolist()
        [100.0, 90.0, nan]
        >>> apart_from_fetus(centres[::-1], [1.0, 1.0, 1.0], uploaded=[True, True, True]).round(1).tolist()   # a twin's mask first
        [90.0, nan, nan]
    """
    masks = [np.asarray(c, np.float64) for c, own in zip(centres, uploaded or []) if own and c is not None]
    if masks:                                      # the user's masks decide among themselves
        target = request_centre(masks, [1.0] * len(masks), [])
        target = masks[0] if target is None else target
    else:
        target = request_centre(centres, confidences, [])
    apart = np.full(len(centres), np.nan)
    for i, centre in enumerate(centres):
        distance = np.inf if target is None or centre is None else float(np.linalg.norm(centre - target))
        if np.isfinite(distance) and distance > BRAIN_MOVE_MM:
            apart[i] = distance
    return apart


def near_on_grid(volume: Volume, grid: LocaliserGrid, centre_mm: NDArray) -> NDArray[np.bool_]:
    """The localiser grid's pixels within :data:`CENTRE_REACH_MM` of ``centre_mm`` (scanner mm), as
    ``[n, Hp, Wp]`` maps of the stack (:func:`~service.preprocess.localiser_inputs.target_maps`)."""
    affine = np.asarray(volume.affine, np.float64)
    offset = affine[:3, 3] - np.asarray(centre_mm, np.float64)
    squared = np.zeros(volume.array.shape, np.float32)
    for c in range(3):                   # the voxels' scanner coordinates, one at a time, by broadcasting
        along = [np.arange(n, dtype=np.float32).reshape([-1 if a == axis else 1 for a in range(3)]) * affine[c, axis]
                 for axis, n in enumerate(volume.array.shape)]
        squared += (along[0] + along[1] + along[2] + np.float32(offset[c])) ** 2
    return target_maps(squared <= CENTRE_REACH_MM ** 2, volume, grid) > 0.5


def one_fetus(localiser: Settles, volumes: list[Volume], found: list[tuple[NDArray, LocaliserGrid]],
              settled: list[Settled], fixed: list[NDArray] | None = None) -> list[Settled]:
    """``settled`` (each stack's :meth:`~service.preprocess.localise.Localiser.settle` on its
    network probabilities ``found``) where its brains are one fetus's; otherwise every stack whose
    brain lies farther than :data:`BRAIN_MOVE_MM` from the request's fetus settled again on the brain
    that reaches within :data:`CENTRE_REACH_MM` of that fetus's centre
    (:func:`request_centre`; ``fixed``: the centres of the request's uploaded masks), the other
    fetus's left out of its choice. A stack that saw no brain there keeps its own (a fetus that
    moved farther than :data:`BRAIN_MOVE_MM` between stacks is still found)."""
    centres = [brain_centre_mm(s.mask, v.affine) for s, v in zip(settled, volumes)]
    target = request_centre(centres, [s.confidence for s in settled], list(fixed or []))
    if target is None:
        return list(settled)
    out = []
    for volume, (prob, grid), own, centre in zip(volumes, found, settled, centres):
        if centre is not None and np.linalg.norm(centre - target) <= BRAIN_MOVE_MM:
            out.append(own)                  # settled there already: its best brain is the one that reaches it
            continue
        there = localiser.settle(volume, prob, grid, prefer=near_on_grid(volume, grid, target))
        out.append(there if there.brain_volume_ml > 0 else own)
    return out
