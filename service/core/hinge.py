"""A model calibration's hinge: an error that is nothing up to an onset and grows in proportion beyond.

Two of a pose model's calibrations take this form, each on a level the service measures per
request: the noise error on a stack's input noise (:func:`service.preprocess.noise.noise_error_mm`)
and the frame error on the request's network error (:func:`service.consistency.frame_error.frame_error_mm`).
Both are added in quadrature to the slices' expected errors.

Example:
    >>> hinge_mm([0.5, 2.0, float("nan")], (1.0, 3.0)).tolist()
    [0.0, 3.0, 0.0]
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def hinge_mm(level: ArrayLike, calibration: tuple[float, float] | None) -> NDArray[np.float64]:
    """``slope x max(0, level - onset)`` (mm) for a calibration ``(onset, slope)``; 0 without a
    calibration or where the level is unknown (NaN)."""
    level = np.asarray(level, np.float64)
    if calibration is None:
        return np.zeros_like(level)
    onset, slope = calibration
    return np.where(np.isfinite(level), slope * np.maximum(level - onset, 0.0), 0.0)
