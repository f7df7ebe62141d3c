"""Slices whose brain runs out of the field of view in their plane.

A field of view planned too tight, or a fetus that moved towards its edge, leaves part of the brain
outside some slices: the network then sees a brain with a straight edge, and places the slice
wrongly (tens of millimetres). Such a slice's pixels are sound, its network pose is not; the
images where it crosses other stacks' slices can still place it, so the answer names it and the
stages treat it as any other.

The brain's mask meets the picture's edge in two ways. Cropped tight about the brain (a common
upload: a stack cut to its mask's box), the outline touches the edge where it is tangent to it:
a few millimetres inwards the brain's width there is more than twice its width at the edge (a
round outline's chord grows as the square root of the depth). Cut by the field of view, the
edge runs through the brain: its width at the edge is most of its width a few millimetres in.
:func:`cut_by_field_of_view` tells how deep the edge runs from the two widths, as into a round
outline (:func:`cut_depth_mm`); an outline flat along the edge over more than a centimetre reads
as cut. Where the mask holds the CSF around the brain, a crop tight about the brain cuts the
CSF, as deep as the pose network's mask lies inside the mask: that much is allowed for.

Example (a disc of radius 30 px, cut by the first row, then only touching it):
    >>> yy, xx = np.mgrid[:80, :80]
    >>> cut = ((yy - 20) ** 2 + (xx - 40) ** 2 <= 900)[None]
    >>> touching = ((yy - 30) ** 2 + (xx - 40) ** 2 <= 900)[None]
    >>> cut_by_field_of_view(np.concatenate([cut, touching]), (1.0, 1.0)).tolist()
    [True, False]
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

CUT_BY_FIELD_OF_VIEW = "cut_by_field_of_view"
"""The name of the fault, in the answer's slices and a stream's slices to acquire again."""
EDGE_DEPTH_MM = 5.0
"""How far inside the picture's edge the brain's width is compared with its width at the edge."""
MIN_CUT_DEPTH_MM = 3.0
"""The brain runs out of the picture where the edge runs this far into it or more
(:func:`cut_depth_mm`). An outline tangent to the edge lies about one pixel deep."""
MIN_EDGE_WIDTH_MM = 10.0
"""A brain that meets the edge over less than this is not judged cut: a pole or a sliver there tells
nothing, and the network's picture of it hardly changes."""


def cut_by_field_of_view(masks: NDArray, pixel_mm: tuple[float, float], beyond_mm: float = 0.0) -> NDArray[np.bool_]:
    """``[n]`` which slices of ``masks`` (``[n, H, W]``, the brain's mask of each slice; ``pixel_mm``
    the row and column pitches) have their brain running out of the picture at one of its four
    edges (see the module): its width along the edge at least :data:`MIN_EDGE_WIDTH_MM`, and the
    edge at least :data:`MIN_CUT_DEPTH_MM` into it. ``beyond_mm``: how far the masks' outline lies
    beyond the brain's (a mask that holds the CSF around the brain: a picture cropped tight about
    the brain cuts that far into the mask and leaves the brain whole).

    Example (a disc whose first row the picture cuts 2 px deep: no cut of the brain, or of a mask
    whose CSF rim is 2 mm wide; 8 px deep: a cut of either):
        >>> yy, xx = np.mgrid[:80, :80]
        >>> shallow, deep = (((yy - c) ** 2 + (xx - 40) ** 2 <= 32 ** 2)[None] for c in (30, 24))
        >>> [cut_by_field_of_view(m, (1.0, 1.0), b).tolist() for m in (shallow, deep) for b in (0.0, 2.0)]
        [[False], [False], [True], [True]]
    """
    masks = np.asarray(masks, bool)
    n, h, w = masks.shape
    row_mm, col_mm = (float(p) for p in pixel_mm)
    cut = np.zeros(n, bool)
    for axis, size, across_mm, along_mm in ((1, h, row_mm, col_mm), (2, w, col_mm, row_mm)):
        inward = min(max(1, int(round(EDGE_DEPTH_MM / across_mm))), size - 1)
        if inward < 1:
            continue
        widths = masks.sum(axis=3 - axis) * along_mm           # [n, size]: the brain's width along each line
        for edge, inside in ((0, inward), (size - 1, size - 1 - inward)):
            at_edge, within = widths[:, edge], widths[:, inside]
            deep = (cut_depth_mm(at_edge, within, inward * across_mm) >= MIN_CUT_DEPTH_MM + beyond_mm) \
                | (within <= at_edge)                   # no wider inside: the edge runs through its middle
            cut |= (at_edge >= MIN_EDGE_WIDTH_MM) & deep
    return cut


def cut_depth_mm(at_edge: NDArray, within: NDArray, apart_mm: float) -> NDArray[np.float64]:
    """How far an edge runs into a round outline whose chords along it are ``at_edge`` long and, at
    ``apart_mm`` inside it, ``within`` (mm): the circle through both chords (a chord ``2 sqrt(d (2R -
    d))`` at depth ``d``; its centre ``k`` inside the edge, ``k = ((b^2 - a^2) / 4 + D^2) / 2D``) is
    cut ``sqrt(k^2 + a^2 / 4) - k`` deep. (An outline no wider inside than at the edge fits no such
    circle well; :func:`cut_by_field_of_view` takes it as cut.)

    Example (a circle of radius 20 mm cut 3 mm deep: chords 2 sqrt(3 x 37) and 2 sqrt(8 x 32)):
        >>> round(float(cut_depth_mm(np.array([2 * 111 ** 0.5]), np.array([2 * 256 ** 0.5]), 5.0)[0]), 6)
        3.0
    """
    a2, b2 = np.asarray(at_edge, np.float64) ** 2 / 4, np.asarray(within, np.float64) ** 2 / 4
    k = (b2 - a2 + apart_mm ** 2) / (2 * apart_mm)
    return np.sqrt(k ** 2 + a2) - k
