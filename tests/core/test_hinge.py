"""The calibrations' hinge: nothing up to the onset, the slope beyond, nothing where the level is unknown."""

from __future__ import annotations

import numpy as np

from service.core.hinge import hinge_mm


def test_the_hinge_is_zero_to_the_onset_linear_beyond_and_zero_where_unknown_or_uncalibrated() -> None:
    level = np.array([[0.0, 9.5, 10.5], [29.5, np.nan, -np.inf]])
    out = hinge_mm(level, (9.5, 0.26))
    np.testing.assert_allclose(out, [[0.0, 0.0, 0.26], [5.2, 0.0, 0.0]])
    assert out.shape == level.shape and hinge_mm(level, None).tolist() == np.zeros_like(level).tolist()
    assert hinge_mm(12.0, (9.5, 0.0)) == 0.0
