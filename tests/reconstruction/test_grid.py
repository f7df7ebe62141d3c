"""A grid's box in atlas mm is where its affine puts its first and last voxel centres, and holds the
box it was made for; a box is cut to a limit, or falls back to the limit where they do not meet;
a box of points is at most MAX_EXTENT_MM wide; a volume of more than MAX_VOLUME_VOXELS is refused."""

from __future__ import annotations

import re

import numpy as np
import pytest

from service.core.errors import InvalidParameter
from service.geometry.pose import apply
from service.reconstruction.grid import (FINEST_STEP_MM, MAX_EXTENT_MM, MAX_VOLUME_VOXELS, bounds_of, bounds_within,
                                         check_volume_size, make_grid)


def test_a_grids_box_is_its_corner_voxels_in_atlas_space_and_holds_the_box_asked_for() -> None:
    asked = np.array([[-31.3, 12.0, -4.4], [28.9, 40.5, 37.1]])
    grid = make_grid(0.8, asked)
    corners = apply(grid.affine, np.array([[0.0, 0.0, 0.0], np.array(grid.shape, float) - 1]))
    assert np.allclose(grid.bounds_mm, corners)
    assert np.all(grid.bounds_mm[0] <= asked[0] + 0.8) and np.all(grid.bounds_mm[1] >= asked[1] - 0.8)
    again = make_grid(0.8, grid.bounds_mm)                    # a grid made from its own box is itself
    assert again.shape == grid.shape and np.allclose(again.affine, grid.affine)


def test_a_box_is_cut_to_its_limit_and_falls_back_to_it_where_they_do_not_meet() -> None:
    rng = np.random.default_rng(4)
    for _ in range(50):
        box = np.sort(rng.uniform(-50, 50, (2, 3)), axis=0)
        limit = np.sort(rng.uniform(-50, 50, (2, 3)), axis=0)
        out = bounds_within(box, limit)
        meet = np.all(np.maximum(box[0], limit[0]) < np.minimum(box[1], limit[1]))
        if meet:
            assert np.all(out[0] >= box[0]) and np.all(out[1] <= box[1])
            assert np.all(out[0] >= limit[0]) and np.all(out[1] <= limit[1])
        else:
            assert np.array_equal(out, limit)


def test_a_few_slices_far_away_do_not_stretch_the_field_of_view() -> None:
    rng = np.random.default_rng(5)
    brain = rng.normal(0.0, 25.0, (5000, 3)) + [10.0, -20.0, 5.0]
    astray = rng.uniform(-900.0, 900.0, (40, 3))                    # a few poses sent from far away
    box = bounds_of(np.concatenate([brain, astray]), margin_mm=6.0)
    assert np.all(box[1] - box[0] <= MAX_EXTENT_MM + 1e-9)
    inside = np.all((brain >= box[0]) & (brain <= box[1]), axis=1)
    assert inside.mean() > 0.999                                     # centred where the points are
    plain = bounds_of(brain, margin_mm=6.0)                          # a brain alone keeps its own box
    assert np.allclose(plain, [brain.min(axis=0) - 6.0, brain.max(axis=0) + 6.0])


def test_a_volume_too_large_is_refused_with_the_finest_voxel_size_that_fits() -> None:
    """A volume of more than MAX_VOLUME_VOXELS is refused naming ``resolution_mm``; the voxel size the
    answer suggests fits, a step finer does not."""
    bounds = ([-70.0, -60, -55], [70.0, 60, 55])
    check_volume_size(make_grid(0.8, bounds))
    for asked in (0.21, 0.3, 0.4):
        with pytest.raises(InvalidParameter, match=r"^resolution_mm: the volume's field of view \(140 x 120 x 110 mm") as e:
            check_volume_size(make_grid(asked, bounds))
        finest = float(re.search(r"ask for ([0-9.]+) mm or coarser", str(e.value)).group(1))
        assert make_grid(finest, bounds).size <= MAX_VOLUME_VOXELS < make_grid(finest - FINEST_STEP_MM, bounds).size
