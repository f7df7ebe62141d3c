"""What a brain's slices add in their own plane beyond the head (service.preprocess.slice_trims), on
generated maps: slices that run on into the trunk, a face beside a cap, a moving head kept whole."""

from __future__ import annotations

import numpy as np

from service.preprocess.brain_shape import brain_from_probabilities
from service.preprocess.slice_trims import OUTLIER_MARGIN_MM, trim_growing_caps, trim_outlier_slices
from tests.support.phantoms import ellipsoid_brain_maps


def test_a_slice_that_runs_on_into_the_trunk_keeps_only_the_head() -> None:
    """Sagittal slices through the neck: two of them run on into the fetal body through a neck as wide
    as the head (no waist); they keep what lies near their neighbours' heads."""
    p = ellipsoid_brain_maps(20, size=80)
    head = p >= 0.5
    p[9:11, 14:26, 20:75] = 0.8                                     # the neck and trunk, beside the head
    brain, _ = brain_from_probabilities(p, voxel_ml=0.01, grid_mm=2.5)
    assert not brain[:, :, 40:].any()                               # the trunk is gone
    assert brain[head].all() and (brain & ~head).sum() < 0.03 * head.sum()
    assert np.array_equal(trim_outlier_slices(head, 2.5), head)     # a head alone is left as it is


def test_a_face_beside_the_last_slices_of_a_cap_is_trimmed_and_a_moving_head_is_not() -> None:
    """The last three slices of a coronal cap also hold the face beside the frontal lobes (each wider
    than the slice before it): what lies beyond the margin of the slice nearer the widest one goes,
    the head stays. A head that moves by 4 mm a slice but narrows to its caps keeps every pixel."""
    p = ellipsoid_brain_maps(20, size=80)
    head = p >= 0.5
    p[15:18, 22:40, 30:50] = np.maximum(p[15:18, 22:40, 30:50], 0.8)      # the face, joined to the head
    brain, _ = brain_from_probabilities(p, voxel_ml=0.01, grid_mm=2.5)
    margin = int(round(OUTLIER_MARGIN_MM / 2.5))
    assert brain[head].all()
    assert not brain[15:18, :, 34 + margin + 1:].any()                   # the face past the margin is gone
    moving = np.zeros_like(head)
    for k in range(len(head)):
        moving[k] = np.roll(head[k], 2 * (k % 3 - 1), axis=1)             # +-2 pixels (5 mm) from slice to slice
    assert np.array_equal(trim_growing_caps(moving, 2.5), moving)


def test_a_cap_is_not_judged_against_an_empty_slice() -> None:
    """A component whose middle slice is empty (another rule emptied it) keeps the slices beyond it:
    their growth over nothing says nothing."""
    brain = ellipsoid_brain_maps(20, size=80) >= 0.5
    brain[9:11] = False                                               # the area-weighted middle (9.5) among them
    assert np.array_equal(trim_growing_caps(brain, 2.5), brain)
