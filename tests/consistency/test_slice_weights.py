"""How the stack fit weighs each slice: noise scales, Tukey weights and motion-model votes."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from service.consistency.motion_model import NO_VOTE
from service.consistency.slice_weights import MIN_NOISE_MM, noise_scales, precisions, robust_weights, votes


def test_a_slice_without_an_expected_error_gets_the_largest_usable_one_and_none_falls_under_the_floor() -> None:
    sig = noise_scales(np.array([2.0, np.nan, 0.0, 5.0]), np.array([True, False, True, False]))
    assert sig.tolist() == [2.0, 2.0, MIN_NOISE_MM, 5.0]


def test_residuals_are_weighed_in_units_of_each_slices_expected_error() -> None:
    """The same 9 mm residual is an outlier for a slice expected within 1 mm, not for one expected at 9."""
    r = np.array([1.0, 1.0, 1.0, 9.0, 9.0])
    w = robust_weights(r, np.array([1.0, 1.0, 1.0, 1.0, 9.0]), np.ones(5, bool))
    assert w[3] == 0.0 and w[4] > 0.9
    assert np.allclose(precisions(np.array([1.0, 2.0]), np.ones(2, bool)).mean(), 1.0)


def test_a_slice_far_from_the_others_prediction_gets_no_vote() -> None:
    motion = SimpleNamespace(noise_scale=1.0, model_sd_mm=0.0)
    v = votes(np.array([0.5, 20.0]), motion, np.array([2.0, 2.0]), np.ones(2, bool))
    assert v[1] == NO_VOTE and 2.0 <= v[0] < 2.1
