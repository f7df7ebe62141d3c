"""The window the two-stage localiser experiment runs its full passes on."""

from __future__ import annotations

import numpy as np
import pytest

from model_export.experiments.localiser_window import _window, coarse_to_fine
from service.io.volume import Volume
from service.preprocess.localiser_inputs import MIN_GRID_PX, PAD_MULTIPLE, localiser_inputs


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


def test_a_box_on_the_coarse_grid_lands_where_the_fine_grid_sees_it() -> None:
    """A bright square at a known place in a stack: its edges on the 4 mm grid, mapped to the 2.5 mm
    grid, lie within a coarse pixel of where the 2.5 mm grid shows them."""
    array = np.zeros((120, 100, 6), np.float32)          # 1.2 x 1.0 mm pixels, the square 48-84 / 30-70 px
    array[48:84, 30:70, :] = 1.0
    volume = Volume(array, np.diag([1.2, 1.0, 3.0, 1.0]))
    (coarse, cgrid), (fine, fgrid) = (localiser_inputs(volume, mm) for mm in (4.0, 2.5))
    for axis, other in ((0, 2), (1, 1)):
        seen = lambda x: np.flatnonzero(x[3, 1].max(axis=other - 1) > 0.5)    # noqa: E731 - rows or columns lit
        c, f = seen(coarse), seen(fine)
        lo = coarse_to_fine(c[0], cgrid, fgrid, axis, 4.0, 2.5)
        hi = coarse_to_fine(c[-1] + 1, cgrid, fgrid, axis, 4.0, 2.5)
        assert abs(lo - f[0]) <= 4.0 / 2.5 and abs(hi - (f[-1] + 1)) <= 4.0 / 2.5, (axis, lo, hi, f[0], f[-1])
