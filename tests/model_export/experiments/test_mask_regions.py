"""The mask-regions experiment's geometry: each voxel of a stack placed in the atlas by its own slice's
pose, and the manual mask with another outline over one third of the brain, against poses and
regions simulated here."""

from __future__ import annotations

import numpy as np
import pytest

from model_export.experiments.mask_regions import atlas_coordinates, hybrid
from service.geometry import se3
from service.geometry.pose import make_pose


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_every_voxel_is_placed_by_its_own_slice(axis: int) -> None:
    """A stack whose slices (along ``axis``) each moved by its own rigid motion, with anisotropic
    voxels: every voxel lands where its slice's ``atlas_from_voxel`` puts it."""
    rng = np.random.default_rng(axis)
    shape = (6, 7, 5)
    voxel = np.diag([1.1, 1.2, 3.0, 1.0])
    poses = se3.exp(np.concatenate([rng.normal(0, 0.2, (shape[axis], 3)), rng.normal(0, 10, (shape[axis], 3))], axis=1))
    atlas_from_voxel = poses @ voxel
    where = atlas_coordinates(shape, atlas_from_voxel, axis)
    for index in [(0, 0, 0), (5, 6, 4), (2, 3, 1), (4, 1, 3)]:
        expected = atlas_from_voxel[index[axis]] @ np.array([*index, 1.0])
        assert np.allclose(where[index], expected[:3])


def test_the_outline_is_swapped_over_one_third_of_the_brain_alone() -> None:
    """A brain turned in the atlas: the third swapped is the one whose atlas z lies in the lowest third
    of the manual brain's extent (not of its voxels), whatever the voxel axes; elsewhere the manual mask
    stays."""
    shape = (30, 30, 30)
    turn = make_pose(se3.exp(np.array([0.0, 0.6, 0.0, 0.0, 0.0, 0.0]))[:3, :3], np.zeros(3))
    where = atlas_coordinates(shape, np.repeat(turn[None], shape[2], axis=0), 2)
    manual = np.zeros(shape, bool)
    manual[5:25, 5:25, 5:25] = True
    found = np.zeros(shape, bool)                                   # the other outline: nothing
    covered = np.zeros(shape, bool)
    for third in range(3):
        out = hybrid(manual, found, where, 2, third).astype(bool)
        z = where[..., 2][manual]
        cuts = z.min() + (z.max() - z.min()) * np.array([0.0, 1 / 3, 2 / 3, 1.0])
        band = (where[..., 2] >= cuts[third]) & (where[..., 2] <= cuts[third + 1])
        assert not out[band].any()                                   # swapped out in the band
        assert np.array_equal(out[~band], manual[~band])             # the manual mask elsewhere
        assert (manual & band).sum() > 0.1 * manual.sum()           # a third of the extent holds brain
        covered |= band
    assert covered[manual].all()                                     # the thirds cover the whole brain
