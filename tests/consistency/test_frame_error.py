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


def test_a_stack_that_sees_no_brain_like_the_others_sets_no_frame_error_for_them() -> None:
    """A mask drawn on a stack without a brain (a review's case: a noise stack's network error 66.9 mm
    beside 10-13): its error was every slice's frame error, and none of the request's was accepted.
    A stack a few times noisier than the others, as whole-uterus requests hold, still counts."""
    assert request_network_error_mm([10.0, 13.0, 66.9], [24, 28, 20]) == request_network_error_mm([10.0, 13.0],
                                                                                                [24, 28])
    assert request_network_error_mm([10.0, 41.0], [20, 20]) == pytest.approx(np.sqrt((100 + 41 ** 2) / 2))
    assert request_network_error_mm([66.9], [20]) == pytest.approx(66.9)      # alone, it is the request's


def test_the_frame_error_is_zero_up_to_the_onset_and_grows_by_the_slope_beyond() -> None:
    sigma = np.array([5.0, 13.0, 14.0, 23.0, np.nan])
    np.testing.assert_allclose(frame_error_mm(sigma, (13.0, 0.5)), [0.0, 0.0, 0.5, 5.0, 0.0])
    np.testing.assert_allclose(frame_error_mm(sigma, None), 0.0)
    assert frame_error_mm(sigma, (13.0, 0.0)).max() == 0.0
