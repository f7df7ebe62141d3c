"""A streamed stack's slices as they arrive."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.errors import InvalidParameter
from service.streaming.frames import SliceFrame, StreamedStack, check_frame


def _frame(index: int, step_mm: float = 3.3, thickness_mm: float = 2.0) -> SliceFrame:
    affine = np.diag([1.2, 1.2, thickness_mm, 1.0])
    affine[:3, 3] = [10.0, -5.0, 40.0 + index * step_mm]
    return SliceFrame("axial", index, np.zeros((8, 8), np.float32), affine)


def test_the_step_between_slices_is_measured_from_the_slices_received_not_their_thickness() -> None:
    """Slices 2 mm thick, 3.3 mm apart, received out of order and with gaps: the step is 3.3 mm (the
    file's third column says 2); with one slice there is no step."""
    stack = StreamedStack("axial")
    stack.add(_frame(6))
    assert stack.step_mm() is None
    for k in (0, 3):
        stack.add(_frame(k))
    assert np.isclose(stack.step_mm(), 3.3)


def test_a_slice_whose_affine_is_sheared_is_refused_naming_the_field() -> None:
    """A streamed slice's pixel axes and normal must be at right angles, as a stack file's are
    (`/v1/predict` refuses a sheared sform): the stream would otherwise place its pixels as if they were."""
    check_frame(_frame(0), max_pixels=10_000)                                     # at right angles: taken
    sheared = _frame(0)
    sheared.scanner_from_voxel[:3, :3] = [[1.1, 0.5, 0.0], [0.0, 1.2, 0.0], [0.0, 0.0, 2.0]]
    with pytest.raises(InvalidParameter, match=r"slice\.scanner_from_voxel: its columns are sheared"):
        check_frame(sheared, max_pixels=10_000)
