"""What a brain's slices add in their own plane beyond the head, cut away slice by slice.

A head's cross-sections change little from one slice to the next and shrink from its widest slice to
either cap. On the localiser's per-slice maps ``[n, H, W]`` of one brain's component
(:mod:`service.preprocess.brain_shape`), a slice far wider than its neighbours has run on into its
surroundings (:func:`trim_outlier_slices`: a sagittal slice through a neck as wide as the head, into
the fetal trunk), and a cap's slice wider than its neighbour nearer the middle holds something beside
the head (:func:`trim_growing_caps`: the face beside the frontal lobes). Each keeps what lies within
:data:`OUTLIER_MARGIN_MM` of the regions that guide it (:func:`margin_disk`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

CAP_GROWTH = 1.2
"""A thin slice whose neighbours overlap is still a waist
(:func:`~service.preprocess.brain_shape.cut_at_waists`) where what lies beyond it (the side with less
mass) has a slice wider than this times the two slices past it on the other side: a brain's area
rises to one widest slice and falls, so a cap beyond a poor slice narrows, and a face beyond a skull
base does not (two slices, so that a partly seen slice beside a poor one does not make a cap look wide).
A cap's slice wider than this times its neighbour nearer the middle is trimmed (:func:`trim_growing_caps`)."""
OUTLIER_AREA = 1.5
"""A slice whose area exceeds this times the median of its component's nearest slices (two on each
side) has run on into its surroundings in its own plane (:func:`trim_outlier_slices`); a head's
cross-sections change far less from one slice to the next."""
OUTLIER_MARGIN_MM = 5.0
"""Such a slice keeps only what lies within this distance of its nearest regular slices' regions; so does
a cap's slice wider than its inner neighbour (:func:`trim_growing_caps`)."""

def margin_disk(grid_mm: float) -> NDArray[np.bool_]:
    """The in-plane disk of radius :data:`OUTLIER_MARGIN_MM` (pixels of ``grid_mm``, at least one)."""
    radius = max(1, int(round(OUTLIER_MARGIN_MM / grid_mm)))
    return np.hypot(*np.mgrid[-radius:radius + 1, -radius:radius + 1]) <= radius


def trim_outlier_slices(component: NDArray[np.bool_], grid_mm: float) -> NDArray[np.bool_]:
    """A component of per-slice maps ``[n, H, W]`` whose outlying slices keep only what lies near their
    neighbours.

    A slice whose area exceeds :data:`OUTLIER_AREA` times the median of its nearest slices (two on
    each side, within the component) holds more than the head: along a sagittal slice the brain runs
    on into the fetal trunk through a neck as wide as itself, which no waist shows. Such a slice keeps
    what lies within :data:`OUTLIER_MARGIN_MM` (pixels of ``grid_mm``) of the regions of its
    nearest regular slices on either side.

    Example (slice 3 of a square brain runs on to the right: it keeps the square and 2 pixels more):
        >>> c = np.zeros((7, 30, 40), bool); c[:, 5:15, 5:15] = True; c[3, 5:15, 15:38] = True
        >>> trim_outlier_slices(c, grid_mm=2.5)[3].any(0).nonzero()[0][[0, -1]].tolist()
        [5, 16]
    """
    area = component.reshape(len(component), -1).sum(1)
    if np.count_nonzero(area) < 5:
        return component
    n = len(area)
    outlier = np.zeros(n, bool)
    for k in np.flatnonzero(area):
        near = [j for j in (k - 2, k - 1, k + 1, k + 2) if 0 <= j < n and area[j] > 0]
        outlier[k] = len(near) >= 2 and area[k] > OUTLIER_AREA * np.median(area[near])
    if not outlier.any():
        return component
    regular = np.flatnonzero((area > 0) & ~outlier)
    disk = margin_disk(grid_mm)
    out = component.copy()
    for k in np.flatnonzero(outlier):
        below, above = regular[regular < k], regular[regular > k]
        guides = ([below[-1]] if len(below) else []) + ([above[0]] if len(above) else [])
        if guides:
            out[k] &= ndimage.binary_dilation(component[guides].any(0), structure=disk)
    return out


def trim_growing_caps(component: NDArray[np.bool_], grid_mm: float) -> NDArray[np.bool_]:
    """A component of per-slice maps ``[n, H, W]`` whose slices on either side of its middle (the
    area-weighted mean slice: a head's widest) keep, where they are wider than :data:`CAP_GROWTH`
    times their neighbour nearer the middle, only what lies within :data:`OUTLIER_MARGIN_MM` of that
    neighbour's region (as trimmed), slice by slice outwards.

    A head's cross-sections shrink from its widest slice to either cap; a slice past it that grows
    again holds something beside the head in its own plane, as the face does beside the frontal
    lobes in a coronal stack's last slices, where no waist parts them. The margin leaves the few
    millimetres a head moves between two slices.

    Example (slices 0-6 of a brain that narrows to slice 6, whose slice 5 also holds a face beside it):
        >>> c = np.zeros((7, 30, 40), bool)
        >>> for k, half in enumerate([6, 8, 9, 9, 8, 6, 4]): c[k, 15 - half:15 + half, 15 - half:15 + half] = True
        >>> c[5, 9:21, 21:36] = True
        >>> out = trim_growing_caps(c, grid_mm=2.5)
        >>> int(c[5].sum()), int(out[5].sum()), bool(out[5, :, 30:].any())
        (324, 192, False)
    """
    area = component.reshape(len(component), -1).sum(1)
    if np.count_nonzero(area) < 5:
        return component
    disk = margin_disk(grid_mm)
    out = component.copy()
    middle = int(round(float(np.arange(len(area)) @ area / area.sum())))     # the widest slices' place,
    for step in (1, -1):                                                      # whatever lies beside a cap
        k = middle + step
        while 0 <= k < len(out) and out[k].any() and out[k - step].any():   # no empty slice to grow from
            inner = out[k - step]
            if out[k].sum() > CAP_GROWTH * inner.sum():
                out[k] &= ndimage.binary_dilation(inner, structure=disk)
            k += step
    return out
