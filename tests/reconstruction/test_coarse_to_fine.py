"""Coarse-to-fine reconstruction: convergence from poses that today's slice registration cannot fix.

Every slice's pose is moved about its centre by RMS 10 mm and RMS 10 deg (normal per axis, scale
5.77 mm / 5.77 deg), the "10 mm / 10 deg" scenario of the benchmark on the small phantom. The
1 mm / 1 deg trust radius of the slice registration alone leaves the poses where they started
(measured before this stage existed: 8.2 mm of relative pose error left, 18 dB).

Measured with the coarse-to-fine stages: relative pose error 0.17 mm, 31.3 dB / NCC 0.981 against
the phantom in its true frame (the 0.84 mm absolute error is the common offset of the starting
poses, 0.79 mm, which the reconstruction keeps as its frame), 49 of 52 slices included.
Thresholds: relative error < 1 mm (the issue's target), > 29 dB, NCC > 0.97, 90 % included.
"""

from __future__ import annotations

import numpy as np

from service.reconstruction.pipeline import reconstruct
from tests.reconstruction.helpers import perturb, psnr_ncc, reference_on, relative_pose_error_mm

PER_AXIS = 10.0 / np.sqrt(3.0)


def _split(poses, acquisition):
    return np.split(poses, np.cumsum([len(t) for t in acquisition.truth])[:-1])


def test_converges_from_10_mm_10_deg_per_slice(acquisition):
    truth = acquisition.slice_set()
    start = perturb(truth.atlas_from_voxel, np.random.default_rng(10), PER_AXIS, PER_AXIS, truth.centres())
    ss = acquisition.slice_set(poses=_split(start, acquisition))
    before = relative_pose_error_mm(truth, start, truth.atlas_from_voxel)
    result = reconstruct(ss, resolution_mm=1.0, svr_iterations=3)
    after = relative_pose_error_mm(truth, result.atlas_from_voxel_final, truth.atlas_from_voxel,
                                   result.included)
    ref, mask = reference_on(result.grid, acquisition)
    psnr, ncc = psnr_ncc(result.volume.array, ref, mask)
    assert before > 7.0
    assert after < 1.0
    assert psnr > 29.0 and ncc > 0.97
    assert result.included.sum() >= 0.9 * ss.include.sum()
