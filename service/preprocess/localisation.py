"""What a stack's brain localisation holds, and the masks cut from it: the ``localisation`` of an answer.

A :class:`Localisation` is the brain mask of one stack on the stack's own grid, uploaded (``mask``)
or found by the localiser's network (``network``; :mod:`service.preprocess.localise`), with its
volume, confidence and how it was drawn: a mask that holds the CSF around the brain (the skull's
inside, as the localiser draws it and as manual fetal masks are usually drawn) is cut, for the pose
network, to a tighter brain mask (:meth:`Localisation.pose_mask`), the atlas masks' convention the
pose network learnt. :func:`inset_in_plane` and :func:`grown` move a mask's outline by exact
Euclidean distances on the voxel sizes (the pose network's inset; a margin for other tools).

Example (an uploaded tight brain mask is the pose network's mask as it is; the localiser's is inset):
    >>> m = np.zeros((30, 30, 4), bool); m[5:25, 5:25] = True
    >>> spacing = np.array([1.0, 1.0, 3.0])
    >>> upload = Localisation.of(m, spacing, "mask", 1.0)
    >>> upload.brain_volume_ml, upload.slices_with_brain, int(upload.pose_mask(spacing).sum())
    (4.8, 4, 1600)
    >>> int(Localisation.of(m, spacing, "network", 0.9).pose_mask(spacing).sum())   # 2 mm off each side
    1024
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from service.preprocess.brain_shape import MASK_THRESHOLD, THRESHOLD
from service.preprocess.stack import mask_box, slice_axis_of

POSE_MASK_INSET_MM = 2.0
"""How far inside the localiser's mask (the skull's inside) the pose network's mask lies: the pose
network learnt the atlas's brain masks, which leave out most of the extra-axial CSF around the brain
(about 1-3.5 mm thick), and a mask that holds it costs the poses accuracy."""


@dataclass(frozen=True)
class Localisation:
    """Where a stack's brain is and how it was found (the ``localisation`` object of a response)."""

    mask: NDArray[np.bool_]
    method: str                    # "mask" (uploaded) or "network"
    brain_volume_ml: float
    confidence: float
    slices_with_brain: int
    holds_csf: bool = False
    """The mask is the skull's inside (the brain and the extra-axial CSF around it): the localiser's
    always, an uploaded one when the request says so (``masks_hold_csf``)."""
    pose_region: NDArray[np.bool_] | None = None
    """Where the pose network's mask starts from, where it differs from :attr:`mask`: the localiser's
    probabilities cut at :data:`~service.preprocess.brain_shape.THRESHOLD` (the mask itself is cut
    lower, as manual masks are drawn; the pose network learnt on the cut it has always had)."""

    @classmethod
    def of(cls, mask: NDArray, spacing: NDArray, method: str, confidence: float,
           holds_csf: bool | None = None, pose_region: NDArray | None = None) -> "Localisation":
        """A mask on a stack's grid of voxel sizes ``spacing``, with its volume and slice count
        (``holds_csf`` default: a localiser's mask does, an uploaded one does not)."""
        m = np.asarray(mask) > 0
        axis = slice_axis_of(spacing)
        slices = int(np.count_nonzero(np.moveaxis(m, axis, 0).reshape(m.shape[axis], -1).any(1)))
        csf = method == "network" if holds_csf is None else bool(holds_csf)
        region = None if pose_region is None else np.asarray(pose_region) > 0
        return cls(m, method, float(m.sum() * np.prod(spacing) / 1000.0), float(confidence), slices, csf, region)

    @property
    def brain_region(self) -> NDArray[np.bool_]:
        """What the pose network's mask starts from: :attr:`pose_region` where there is one, else the mask."""
        return self.mask if self.pose_region is None else self.pose_region

    @property
    def pose_inset_mm(self) -> float:
        """How far inside the mask the pose network's mask lies (:meth:`pose_mask`)."""
        return POSE_MASK_INSET_MM if self.holds_csf else 0.0

    @classmethod
    def found(cls, probability: NDArray, spacing: NDArray, confidence: float) -> "Localisation":
        """The localiser's answer from its brain probabilities on the stack's grid: the mask cut at
        :data:`~service.preprocess.brain_shape.MASK_THRESHOLD`, its :attr:`pose_region` at
        :data:`~service.preprocess.brain_shape.THRESHOLD`."""
        return cls.of(probability >= MASK_THRESHOLD, spacing, "network", confidence,
                      pose_region=probability >= THRESHOLD)

    def pose_mask(self, spacing: NDArray, axis: int | None = None) -> NDArray[np.bool_]:
        """The mask the pose network's slices are cut with: a tight brain mask as it is; one that holds
        the CSF around the brain (the localiser's, or an upload the request says holds it) without its outer
        :data:`POSE_MASK_INSET_MM` in the plane of the slices along ``axis`` (default: the thick one),
        the brain as the atlas masks the pose network learnt from draw it; the localiser's from its
        :attr:`pose_region`."""
        region = self.brain_region
        if not self.holds_csf or not region.any():
            return region
        return inset_in_plane(region, np.asarray(spacing, np.float64), POSE_MASK_INSET_MM, axis)

    def report(self) -> dict:
        """The ``localisation`` object of a ``/v1/predict`` stack."""
        return {"method": self.method, "brain_volume_ml": round(self.brain_volume_ml, 1),
                "confidence": round(self.confidence, 3), "pose_mask_inset_mm": self.pose_inset_mm}


def inset_in_plane(mask: NDArray, spacing: NDArray, inset_mm: float, axis: int | None = None) -> NDArray[np.bool_]:
    """``mask`` without the pixels within ``inset_mm`` of its outside, in the plane of each slice along
    ``axis`` (default: the thick one), by exact Euclidean distances on the voxel sizes ``spacing``:
    an erosion by the in-plane disc of the offsets within ``inset_mm`` (outside the array counts as
    outside), which on a fine grid costs half a distance transform. Pixels coarser than the inset
    lose one pixel along each in-plane axis (a disc of the coarser pixel's size): by the inset alone
    they kept every pixel.

    Example (a 20 x 20 mm square of 1 mm pixels loses 2 mm on each side):
        >>> m = np.zeros((30, 30, 3), bool); m[5:25, 5:25] = True
        >>> out = inset_in_plane(m, np.array([1.0, 1.0, 3.0]), 2.0)
        >>> int(out[:, :, 1].sum()), bool(out[:, :, 0].sum() == out[:, :, 1].sum())
        (256, True)
    """
    mask = np.asarray(mask, bool)
    box = mask_box(mask, [0, 0, 0])
    if box is None:
        return mask.copy()
    axis = slice_axis_of(spacing) if axis is None else axis
    sampling = np.asarray(spacing, np.float64)
    # at least one pixel along each in-plane axis: pixels coarser than the inset would keep it all
    radius = max(inset_mm, max(float(sampling[k]) for k in range(3) if k != axis)) if inset_mm > 0 else 0.0
    reach = [0 if k == axis else int(np.floor(radius / sampling[k] + 1e-9)) for k in range(3)]
    offsets = np.meshgrid(*[np.arange(-r, r + 1) * sampling[k] for k, r in enumerate(reach)], indexing="ij")
    disc = sum(o ** 2 for o in offsets) <= radius ** 2 + 1e-9
    inside = np.pad(mask[box], [(r, r) for r in reach])
    out = np.zeros_like(mask)
    out[box] = ndimage.binary_erosion(inside, disc)[tuple(slice(r, len_ - r) for r, len_ in zip(reach, inside.shape))]
    return out


def grown(mask: NDArray, spacing: NDArray, margin_mm: float) -> NDArray[np.bool_]:
    """``mask`` with every voxel whose centre lies within ``margin_mm`` of it, by exact Euclidean
    distances on the voxel sizes ``spacing`` (across thick slices only where the margin reaches the
    next slice's centre): a mask drawn to another convention (the skull's outer edge, a margin for a
    reconstruction tool) from the localiser's, which is the skull's inside.

    Example (a 10 x 10 mm square of 1 mm pixels, 3 mm slices, grown by 2 mm: 14 x 14 pixels less the
    three beyond 2 mm at each corner, no slice added):
        >>> m = np.zeros((20, 20, 5), bool); m[5:15, 5:15, 2] = True
        >>> out = grown(m, np.array([1.0, 1.0, 3.0]), 2.0)
        >>> int(out[:, :, 2].sum()), int(out.sum() - out[:, :, 2].sum())
        (184, 0)
    """
    mask = np.asarray(mask, bool)
    found = np.argwhere(mask)
    if margin_mm <= 0 or len(found) == 0:
        return mask.copy()
    sampling = np.asarray(spacing, np.float64)
    reach = np.ceil(margin_mm / sampling).astype(int) + 1
    lo, hi = np.maximum(found.min(0) - reach, 0), np.minimum(found.max(0) + reach + 1, mask.shape)
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    out = np.zeros_like(mask)
    out[box] = ndimage.distance_transform_edt(~mask[box], sampling=sampling) <= margin_mm
    return out


REGION_FILL = 0.95
"""An uploaded mask that fills at least this share of its bounding box is a region of interest drawn
around the head (a box in a viewer), not a brain's outline, which fills far less of its box
(docs/localisation.md)."""
REGION_REPEAT = 0.99
"""An uploaded mask whose slices along one voxel axis hold the same cross-section, at least this share
of their union common to all of them, is a shape drawn in one plane and extruded (a box, an elliptic
cylinder, a contour copied to every slice: the share is 1): a region of interest. A brain's
cross-sections change from slice to slice, even over the few central slices of a stack that covers
part of it (docs/localisation.md)."""
MIN_REGION_ML = 100.0
"""A region under this volume cannot hold the youngest fetal head the service serves: such a mask is
taken as the brain it marks (docs/localisation.md)."""


def drawn_shape_scores(mask: NDArray) -> tuple[float, float]:
    """How much a mask looks drawn rather than segmented, within its bounding box: the share of the
    box it fills, and the share of its cross-sections' union common to all of them along the voxel
    axis where that share is largest (1 for a shape extruded along that axis).

    Example (a box; an elliptic cylinder; a sphere):
        >>> x, y, z = np.ogrid[:40, :40, :40]
        >>> box = np.ones((20, 30, 10), bool)
        >>> cylinder = np.broadcast_to(((x - 19.5) / 20) ** 2 + ((y - 19.5) / 20) ** 2 <= 1, (40, 40, 40))
        >>> sphere = ((x - 19.5) / 20) ** 2 + ((y - 19.5) / 20) ** 2 + ((z - 19.5) / 20) ** 2 <= 1
        >>> [tuple(round(v, 2) for v in drawn_shape_scores(m)) for m in (box, cylinder, sphere)]
        [(1.0, 1.0), (0.79, 1.0), (0.52, 0.05)]
    """
    m = np.asarray(mask, bool)
    ends = [np.flatnonzero(m.any(axis=tuple(a for a in range(m.ndim) if a != k))) for k in range(m.ndim)]
    if any(not len(e) for e in ends):
        return 0.0, 0.0
    box = m[tuple(slice(e[0], e[-1] + 1) for e in ends)]
    repeat = max(float(box.all(axis=k).sum()) / float(box.any(axis=k).sum()) for k in range(box.ndim))
    return float(box.mean()), repeat


def is_region_of_interest(mask: NDArray, spacing: NDArray) -> bool:
    """Whether an uploaded mask is a region of interest around the head, not a brain's outline: a box
    (:data:`REGION_FILL`) or a shape extruded along a voxel axis (:data:`REGION_REPEAT`: an elliptic
    cylinder, a contour drawn in one slice and copied to the others) of :data:`MIN_REGION_ML` or more
    (:func:`drawn_shape_scores`). The brain is to be found inside it, not the mask taken for the brain.
    An ellipsoid drawn around the head is not told from a brain's mask this way (a smooth brain-like
    mask fills an ellipsoid nearly as well) and is taken for the brain.

    Example (a box of 60 x 60 x 20 voxels of 1 x 1 x 3 mm, 216 ml; a cylinder; the ellipsoid inside the box):
        >>> box = np.zeros((80, 80, 30), bool); box[10:70, 10:70, 5:25] = True
        >>> x, y, z = np.ogrid[:80, :80, :30]
        >>> cylinder = box & (((x - 39.5) / 30) ** 2 + ((y - 39.5) / 30) ** 2 <= 1)
        >>> ellipsoid = ((x - 39.5) / 30) ** 2 + ((y - 39.5) / 30) ** 2 + ((z - 14.5) / 10) ** 2 <= 1
        >>> [is_region_of_interest(m, np.array([1.0, 1.0, 3.0])) for m in (box, cylinder, ellipsoid)]
        [True, True, False]
    """
    m = np.asarray(mask, bool)
    count = int(np.count_nonzero(m))
    if not count or count * float(np.prod(spacing)) / 1000.0 < MIN_REGION_ML:
        return False
    fill, repeat = drawn_shape_scores(m)
    return fill >= REGION_FILL or repeat >= REGION_REPEAT


def within_region(found: Localisation, region: NDArray, spacing: NDArray) -> Localisation:
    """The localiser's ``found`` brain kept to the user's ``region`` of interest (its confidence scaled
    by the share of the brain kept): the region says where the fetus's head is.

    Example (a brain half outside the region; the pose network's region, larger, kept to it too):
        >>> m = np.zeros((20, 20, 4), bool); m[5:15, 5:15] = True
        >>> region = np.zeros_like(m); region[:10] = True
        >>> pose_region = np.zeros_like(m); pose_region[3:17, 3:17] = True
        >>> found = Localisation.of(m, np.ones(3), "network", 0.8, pose_region=pose_region)
        >>> kept = within_region(found, region, np.ones(3))
        >>> kept.method, kept.brain_volume_ml, round(kept.confidence, 2)
        ('network', 0.2, 0.4)
        >>> bool(kept.pose_region[region].any()), bool(kept.pose_region[~region].any())
        (True, False)
    """
    r = np.asarray(region, bool)
    kept = found.mask & r
    share = float(kept.sum()) / max(float(found.mask.sum()), 1.0)
    pose_region = None if found.pose_region is None else found.pose_region & r
    return Localisation.of(kept, spacing, found.method, found.confidence * share, found.holds_csf, pose_region)
