"""A ``/v1/predict`` answer's ITK transforms are a reconstruction job's: the same ``.tfm`` text and the
same composition, checked against the service's writer on random poses (the geometry itself is
checked end to end against a simulated truth in ``tests/api/test_predict_geometry.py``)."""

from __future__ import annotations

import numpy as np

from client.slice_transforms import stack_from_atlas_lps, tfm_text
from service.geometry import frames, se3
from service.reconstruction import export


def test_the_text_and_the_composition_are_a_jobs() -> None:
    rng = np.random.default_rng(3)
    for _ in range(5):
        atlas_from_voxel = se3.exp(rng.normal(size=6) * [0.5, 0.5, 0.5, 30, 30, 30]) @ np.diag([0.9, 1.1, 3.5, 1.0])
        scanner_from_voxel = se3.exp(rng.normal(size=6) * [0.5, 0.5, 0.5, 30, 30, 30]) @ np.diag([-0.9, 1.1, 3.5, 1.0])
        ours = stack_from_atlas_lps(atlas_from_voxel, scanner_from_voxel)
        job = frames.LPS_FROM_RAS @ export.scanner_from_atlas(atlas_from_voxel[None], scanner_from_voxel)[0] \
            @ frames.RAS_FROM_LPS
        np.testing.assert_allclose(ours, job, atol=1e-12)
        assert tfm_text(ours) == export.tfm_text(ours)
