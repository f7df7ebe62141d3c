"""Slices whose brain runs out of the field of view in their plane.

A field of view planned too tight, or a fetus that moved towards its edge, leaves part of the brain
outside some slices: the network then sees a brain with a straight edge, and places the slice
wrongly (tens of millimetres). Such a slice's pixels are sound, its network pose is not; the
images where it crosses other stacks' slices can still place it, so the answer names it and the
stages treat it as any other.

The brain's mask meets the picture's edge in two ways. Cropped tight about the brain (a common
upload: a stack cut to its mask's box), the outline touches the edge where it is tangent to it:
one pixel inwards the brain's width there grows fast (a round outline's chord grows as the
square root of the depth), and a few millimetres in it is more than twice the width at the edge.
Cut by the field of view, the edge runs through the brain: its width at the edge is most of its
width a few millimetres in. :func:`cut_by_field_of_view` compares the two.

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
EDGE_WIDTH_SHARE = 0.6
"""The brain runs out of the picture where its width along an edge is at least this share of its width
:data:`EDGE_DEPTH_MM` inside it: a round outline tangent to the edge at one pixel's depth gives 0.4
to 0.45 for pixels of 1 to 1.25 mm (the square root of the depths' ratio), an edge through the brain
3 mm deep about 0.6, deeper 0.8 and more."""
MIN_EDGE_WIDTH_MM = 10.0
"""A brain that meets the edge over less than this is not judged cut: a pole or a sliver there tells
nothing, and the network's picture of it hardly changes."""


def cut_by_field_of_view(masks: NDArray, pixel_mm: tuple[float, float]) -> NDArray[np.bool_]:
    """``[n]`` which slices of ``masks`` (``[n, H, W]``, the brain's mask of each slice; ``pixel_mm``
    the row and column pitches) have their brain running out of the picture at one of its four
    edges (see the module): its width along the edge at least :data:`MIN_EDGE_WIDTH_MM` and at
    least :data:`EDGE_WIDTH_SHARE` of its width :data:`EDGE_DEPTH_MM` inside."""
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
            cut |= (at_edge >= MIN_EDGE_WIDTH_MM) & (at_edge >= EDGE_WIDTH_SHARE * within)
    return cut
