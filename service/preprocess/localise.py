"""Automatic brain localisation for stacks uploaded without a mask (a heuristic; see its limits).

Method (on T2-weighted fetal stacks, where the fetal head is soft tissue bathed in bright
amniotic fluid and CSF):

1. smooth lightly; split intensities with a three-class Otsu (SimpleITK) into background, tissue
   and fluid (the brightest class);
2. tissue = signal that is not fluid, opened in-plane to cut thin bridges; its 3D connected
   components are candidates;
3. a candidate must not touch the in-plane border of the field of view (the maternal body does;
   the fetal head, surrounded by fluid, does not) and have an equivalent radius of 15-60 mm; among
   those, the most compact one closest to a 35 mm radius wins;
4. the winner is hole-filled slice by slice and dilated by 3 mm (to take in the surrounding CSF).

Failure modes (measured on the test phantoms; no real uncropped fetal stacks are in this
repository's data): a fetal head touching the uterine wall or the field-of-view edge in-plane is
rejected at step 3 and the method falls back to the most compact component of any size, which may
be maternal tissue; a fetal body of brain size can win over the head; very low-contrast (early
gestation, heavy bias) stacks can merge fluid and tissue classes. Clients that need reliability
upload masks (``masks`` field); the response flags slices whose mask is empty.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from numpy.typing import NDArray
from scipy import ndimage

from service.io.volume import Volume, to_sitk

RADIUS_MM = (15.0, 60.0)
TARGET_RADIUS_MM = 35.0
DILATE_MM = 3.0


def _three_classes(volume: Volume) -> NDArray[np.uint8]:
    image = sitk.SmoothingRecursiveGaussian(sitk.Cast(to_sitk(volume), sitk.sitkFloat32), 1.0)
    labels = sitk.OtsuMultipleThresholds(image, numberOfThresholds=2, numberOfHistogramBins=128)
    return sitk.GetArrayFromImage(labels).transpose(2, 1, 0).astype(np.uint8)


def localise_brain(volume: Volume, slice_axis: int) -> NDArray[np.bool_]:
    """A brain mask on the stack's grid (see the module docstring for the method and its limits)."""
    classes = _three_classes(volume)
    inplane = [ax for ax in range(3) if ax != slice_axis]
    struct = np.zeros((3, 3, 3), bool)
    struct[tuple(slice(None) if ax in inplane else 1 for ax in range(3))] = True
    tissue = ndimage.binary_opening(classes == 1, structure=struct)
    labels, n = ndimage.label(tissue)
    if n == 0:
        return np.zeros(classes.shape, bool)
    ids = np.arange(1, n + 1)
    voxel_mm3 = float(np.prod(volume.spacing))
    counts = ndimage.sum_labels(np.ones_like(labels), labels, ids)
    radius = np.cbrt(3.0 * counts * voxel_mm3 / (4.0 * np.pi))
    border = np.zeros(n + 1, bool)
    for ax in inplane:
        for edge in (0, -1):
            border[np.unique(np.take(labels, edge, axis=ax))] = True
    boxes = ndimage.find_objects(labels)
    box_mm3 = np.array([np.prod([(s.stop - s.start) for s in b]) for b in boxes]) * voxel_mm3
    compact = counts * voxel_mm3 / box_mm3                       # 1 for a box, ~0.52 for a sphere
    ok = (~border[1:]) & (radius >= RADIUS_MM[0]) & (radius <= RADIUS_MM[1])
    score = compact - np.abs(radius - TARGET_RADIUS_MM) / TARGET_RADIUS_MM
    pool = ok if ok.any() else (counts > 0.01 * counts.max())
    best = ids[pool][np.argmax(score[pool])]
    mask = labels == best
    mask = np.moveaxis(ndimage.binary_fill_holes(np.moveaxis(mask, slice_axis, 0), structure=np.ones((1, 3, 3))),
                       0, slice_axis)
    iters = max(1, int(round(DILATE_MM / min(volume.spacing[inplane]))))
    return ndimage.binary_dilation(mask, structure=struct, iterations=iters)
