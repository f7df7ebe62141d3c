"""Accept flags and their reasons, in order of precedence (the contract's ``reason`` values)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

EMPTY, DEGENERATE, OUTSIDE, HIGH_VARIANCE = "empty", "degenerate_anchor_points", "outside_atlas", "high_variance"
INCONSISTENT, HIGH_EXPECTED_ERROR = "inconsistent_with_stack", "high_expected_error"
REASONS = (EMPTY, DEGENERATE, OUTSIDE, INCONSISTENT, HIGH_EXPECTED_ERROR, HIGH_VARIANCE)

MIN_MASK_FRACTION = 0.01
"""A network input whose region of interest covers less than 1 % of it is ``empty``."""
ATLAS_RADIUS_MM = 70.0
"""Slice centres further than this from the atlas brain centre are ``outside_atlas`` (the largest
atlas brains reach ~60 mm from their centre)."""
ATLAS_CENTRE_MM = np.array([0.0, 2.0, 8.0])


def over_limits(variance: NDArray, threshold: float, expected_error_mm: NDArray | None = None,
                max_expected_error_mm: float | None = None) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Which slices are over the expected-error limit (``high_expected_error``; a NaN expected error,
    or none, is not judged) and over the variance threshold (``high_variance``; NaN variance is).

    Example:
        >>> [f.tolist() for f in over_limits(np.array([1.0, np.nan]), 5.0, np.array([6.0, np.nan]), 4.0)]
        [[True, False], [False, True]]
    """
    high = ~(np.asarray(variance) <= threshold)
    if expected_error_mm is None or max_expected_error_mm is None:
        return np.zeros(len(high), bool), high
    return np.asarray(expected_error_mm, dtype=np.float64) > max_expected_error_mm, high


def reasons(mask_fraction: NDArray, degenerate: NDArray, translation_mm: NDArray, variance: NDArray,
            threshold: float, inconsistent: NDArray | None = None, expected_error_mm: NDArray | None = None,
            max_expected_error_mm: float | None = None) -> list[str | None]:
    """The reason each slice is not accepted (``None`` = accepted).

    ``expected_error_mm`` is the returned pose's calibrated expected E.D. (after every stage);
    above ``max_expected_error_mm`` the slice is ``high_expected_error``. A slice without one (NaN,
    or none given) and a threshold of None are judged by the variance alone.

    Example:
        >>> reasons(np.array([0.5, 0.5, 0.5]), np.zeros(3, bool), np.zeros((3, 3)), np.array([1.0, 1.0, 9.0]),
        ...         5.0, expected_error_mm=np.array([2.0, 7.0, np.nan]), max_expected_error_mm=4.0)
        [None, 'high_expected_error', 'high_variance']
    """
    empty = np.asarray(mask_fraction) < MIN_MASK_FRACTION
    outside = np.linalg.norm(np.asarray(translation_mm) - ATLAS_CENTRE_MM, axis=-1) > ATLAS_RADIUS_MM
    bad = np.zeros(len(empty), bool) if inconsistent is None else np.asarray(inconsistent, bool)
    unsure, high = over_limits(variance, threshold, expected_error_mm, max_expected_error_mm)
    flags = np.stack([empty, np.asarray(degenerate, bool), outside, bad, unsure, high], axis=1)
    first = np.argmax(flags, axis=1)
    return [REASONS[f] if flags[i, f] else None for i, f in enumerate(first)]
