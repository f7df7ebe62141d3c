"""A request's frame error: its network error over its stacks, and the calibrated hinge on it."""

from __future__ import annotations

import numpy as np
import pytest

from service.consistency.frame_error import frame_error_mm, request_network_error_mm


def test_the_request_s_network_error_weighs_each_stack_by_its_slices_and_skips_stacks_without_a_fit() -> None:
    assert request_network_error_mm([12.0], [40]) == pytest.approx(12.0)
    assert request_network_error_mm([6.0, 18.0], [10, 10]) == pytest.approx(np.sqrt(180.0))
    assert request_network_error_mm([6.0, 18.0], [30, 10]) == pytest.approx(np.sqrt((30 * 36 + 10 * 324) / 40))
    assert request_network_error_mm([6.0, np.nan], [10, 99]) == pytest.approx(6.0)
    assert np.isnan(request_network_error_mm([], []))
    assert np.isnan(request_network_error_mm([8.0], [0]))            # a stack without a posed slice


def test_the_frame_error_is_zero_up_to_the_onset_and_grows_by_the_slope_beyond() -> None:
    sigma = np.array([5.0, 13.0, 14.0, 23.0, np.nan])
    np.testing.assert_allclose(frame_error_mm(sigma, (13.0, 0.5)), [0.0, 0.0, 0.5, 5.0, 0.0])
    np.testing.assert_allclose(frame_error_mm(sigma, None), 0.0)
    assert frame_error_mm(sigma, (13.0, 0.0)).max() == 0.0
