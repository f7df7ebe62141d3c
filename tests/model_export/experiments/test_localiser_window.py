"""The window the two-stage localiser experiment runs its full passes on."""

from __future__ import annotations

import pytest

from model_export.experiments.localiser_window import _window
from service.preprocess.localiser_inputs import MIN_GRID_PX, PAD_MULTIPLE


@pytest.mark.parametrize(("lo", "hi", "n"), [(40.3, 70.2, 128), (0.0, 100.0, 128), (100.0, 127.0, 128),
                                              (-5.0, 20.0, 160), (10.0, 150.0, 144)])
def test_the_window_holds_the_box_in_whole_blocks_of_at_least_the_smallest_canvas(lo: float, hi: float, n: int) -> None:
    a, b = _window(lo, hi, n)
    assert 0 <= a < b <= n
    assert (b - a) % PAD_MULTIPLE == 0 or (a, b) == (0, n)
    assert b - a >= min(MIN_GRID_PX, n)
    assert a <= max(lo, 0) and b >= min(hi, n) - 1e-9


def test_a_box_wider_than_the_canvas_takes_the_whole_canvas() -> None:
    assert _window(-10.0, 200.0, 128) == (0, 128)
