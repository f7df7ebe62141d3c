"""Each slice's head ellipse (service.preprocess.head_ellipses), on generated probability maps."""

from __future__ import annotations

import numpy as np

from service.preprocess.slice_trims import trim_outlier_slices
from service.preprocess.head_ellipses import trim_to_head_ellipses
from tests.support.phantoms import ellipsoid_brain_maps


def test_slices_that_run_on_together_lose_what_lies_outside_their_head_ellipse() -> None:
    """Four neighbouring slices run on into the neck together (no slice is an outlier among its
    neighbours): each keeps its head's ellipse; the head alone keeps all but a sliver."""
    p = ellipsoid_brain_maps(20, size=80)
    head = p >= 0.5
    p[7:12, 16:24, 20:60] = np.maximum(p[7:12, 16:24, 20:60], 0.8)  # a neck 20 mm wide, 100 mm long
    component = p >= 0.5
    assert np.array_equal(trim_outlier_slices(component, 2.5), component)
    trimmed = trim_to_head_ellipses(component, 2.5)
    assert not trimmed[:, :, 40:].any() and trimmed[head].mean() > 0.99
    assert (trim_to_head_ellipses(head, 2.5) ^ head).sum() < 0.01 * head.sum()
