"""In-plane binning of slices (``SliceSet.binned``): geometry against simulated ground truth.

A stack sampled from an intensity that is linear in atlas position (any oblique affine, any slice
axis, a mask cutting blocks) must bin to values equal to that linear intensity at the binned
pixels' atlas positions: this holds only if each binned pixel sits exactly at the centre of its
block (the centroid of its masked pixels), for the acquisition affine and for any other pose.
"""

from __future__ import annotations

import numpy as np
import pytest

from service.geometry import se3
from service.geometry.pose import make_pose
from service.io.volume import Volume
from service.reconstruction.forward import inplane_sigma_mm
from service.reconstruction.config import ReconstructionConfig
from service.reconstruction.pipeline import reconstruct
from service.reconstruction.slices import SliceSet, inplane_bin_factors

GRADIENT = np.array([0.7, -1.3, 2.1])
OFFSET = 50.0


def ramp_stack(axis: int, shape: tuple[int, int, int], seed: int) -> tuple[Volume, np.ndarray, np.ndarray]:
    """An oblique stack whose voxel values are ``GRADIENT . atlas position + OFFSET``, a ragged mask, poses."""
    rng = np.random.default_rng(seed)
    spacing = np.full(3, 0.55)
    spacing[axis] = 3.0
    rot = se3.so3_exp(rng.normal(scale=0.5, size=3))
    affine = make_pose(rot @ np.diag(spacing), rng.normal(scale=5.0, size=3))
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1).astype(np.float64)
    pos = ijk @ affine[:3, :3].T + affine[:3, 3]
    values = pos @ GRADIENT + OFFSET
    mask = rng.random(shape) > 0.3                       # cuts many blocks to 1-3 pixels
    mats = np.repeat(affine[None], shape[axis], 0)
    return Volume(values.astype(np.float32), affine), mask, mats


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_binned_pixels_sit_at_their_block_centre(axis):
    shape = [9, 11, 7]
    shape[axis] = 4
    vol, mask, mats = ramp_stack(axis, tuple(shape), seed=axis)
    ss = SliceSet.from_stacks([(vol, mask, mats, np.ones(4, bool))])
    b = ss.binned(2)
    # the stack's intensity scaling is linear too: binned values = the scaled ramp at the binned positions
    scale = float(ss.values[0] / (ss.positions()[0] @ GRADIENT + OFFSET))
    expect = (b.positions() @ GRADIENT + OFFSET) * scale
    np.testing.assert_allclose(b.values, expect, rtol=1e-4)
    # under any other pose, a binned pixel is the mean atlas position of its block's pixels
    rng = np.random.default_rng(9)
    poses = make_pose(se3.so3_exp(rng.normal(size=(4, 3))), rng.normal(scale=10.0, size=(4, 3))) @ mats
    full = ss.positions(poses)
    sid = ss.slice_id
    vox = ss.voxel.astype(int)
    p, q = [a for a in range(3) if a != axis]
    key = np.stack([sid, vox[:, q] // 2, vox[:, p] // 2], -1)
    _, block = np.unique(key, axis=0, return_inverse=True)
    block = block.reshape(-1)
    centroid = np.stack([np.bincount(block, full[:, d]) for d in range(3)], -1) / np.bincount(block)[:, None]
    np.testing.assert_allclose(b.positions(poses), centroid, atol=1e-4)
    # full blocks: the voxel coordinate is exactly the 2 x 2 block's centre
    counts = np.bincount(block)
    full_blocks = counts == 4
    assert full_blocks.any()
    frac = b.voxel[full_blocks][:, [p, q]] - 0.5
    np.testing.assert_array_equal(frac % 2, 0)
    # grouping by slice kept, per-slice arrays untouched, PSF widened
    assert np.all(np.diff(b.slice_id) >= 0)
    assert b.n_pixels == len(counts)
    np.testing.assert_array_equal(b.atlas_from_voxel, ss.atlas_from_voxel)
    assert inplane_sigma_mm(b) > inplane_sigma_mm(ss)


def test_binning_factor_one_is_identity_and_mixed_factors():
    vol, mask, mats = ramp_stack(2, (8, 8, 4), seed=3)
    ss = SliceSet.from_stacks([(vol, mask, mats, np.ones(4, bool))] * 2)
    assert ss.binned(1) is ss
    f = np.array([2] * 4 + [1] * 4)
    b = ss.binned(f)
    second = ss.stack_index[ss.slice_id] == 1
    np.testing.assert_array_equal(b.values[b.stack_index[b.slice_id] == 1], ss.values[second])
    assert (b.stack_index[b.slice_id] == 0).sum() < (~second).sum()
    np.testing.assert_allclose(b.pixel_mm[4:], ss.pixel_mm[4:])


def test_bin_factors_follow_the_voxel_size():
    vol, mask, mats = ramp_stack(2, (8, 8, 4), seed=4)
    ss = SliceSet.from_stacks([(vol, mask, mats, np.ones(4, bool))])
    assert inplane_bin_factors(ss, 0.8).tolist() == [2] * 4
    assert inplane_bin_factors(ss, 0.7).tolist() == [1] * 4


def test_reconstruct_bins_fine_pixels_and_keeps_per_slice_outputs():
    vol, mask, mats = ramp_stack(2, (16, 16, 4), seed=5)
    ss = SliceSet.from_stacks([(vol, None, mats, np.ones(4, bool))])
    on = reconstruct(ss, resolution_mm=1.0, svr_iterations=0)
    off = reconstruct(ss, resolution_mm=1.0, svr_iterations=0, config=ReconstructionConfig(inplane_binning=False))
    assert on.atlas_from_voxel_final.shape == off.atlas_from_voxel_final.shape == (4, 4, 4)
    assert on.included.tolist() == off.included.tolist() == [True] * 4
    inside = (on.volume.array > 0) & (off.volume.array > 0)
    assert np.corrcoef(on.volume.array[inside], off.volume.array[inside])[0, 1] > 0.99
