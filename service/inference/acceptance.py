"""Accept flags and their reasons, in order of precedence (the contract's ``reason`` values)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

EMPTY, DEGENERATE, OUTSIDE, HIGH_VARIANCE = "empty", "degenerate_anchor_points", "outside_atlas", "high_variance"
INCONSISTENT = "inconsistent_with_stack"
REASONS = (EMPTY, DEGENERATE, OUTSIDE, INCONSISTENT, HIGH_VARIANCE)

MIN_MASK_FRACTION = 0.01
"""A network input whose region of interest covers less than 1 % of it is ``empty``."""
ATLAS_RADIUS_MM = 70.0
"""Slice centres further than this from the atlas brain centre are ``outside_atlas`` (the largest
atlas brains reach ~60 mm from their centre)."""
ATLAS_CENTRE_MM = np.array([0.0, 2.0, 8.0])


def reasons(mask_fraction: NDArray, degenerate: NDArray, translation_mm: NDArray, variance: NDArray,
            threshold: float, inconsistent: NDArray | None = None) -> list[str | None]:
    """The reason each slice is not accepted (``None`` = accepted)."""
    empty = np.asarray(mask_fraction) < MIN_MASK_FRACTION
    outside = np.linalg.norm(np.asarray(translation_mm) - ATLAS_CENTRE_MM, axis=-1) > ATLAS_RADIUS_MM
    high = ~(np.asarray(variance) <= threshold)            # NaN variance is not accepted either
    bad = np.zeros(len(empty), bool) if inconsistent is None else np.asarray(inconsistent, bool)
    flags = np.stack([empty, np.asarray(degenerate, bool), outside, bad, high], axis=1)
    first = np.argmax(flags, axis=1)
    return [REASONS[f] if flags[i, f] else None for i, f in enumerate(first)]
