"""The refinement benchmark's frame: the common error of a set of poses, in the direction the
volume metrics need (truth atlas -> reconstruction is its inverse), against a simulated one."""

from __future__ import annotations

import numpy as np

from model_export.experiments.refine_bench import to_truth_frame
from service.geometry import se3
from service.geometry.pose import apply


def test_the_common_error_of_poses_is_found_in_the_direction_of_the_truth() -> None:
    rng = np.random.default_rng(3)
    truth = se3.exp(np.concatenate([rng.normal(0, 0.5, (30, 3)), rng.normal(0, 25, (30, 3))], axis=1))
    recon_from_truth = se3.exp(np.array([0.02, -0.04, 0.03, 2.0, -1.0, 1.5]))     # the reconstruction's frame
    posed = recon_from_truth[None] @ truth
    frame = to_truth_frame(posed, truth)
    assert np.allclose(frame @ recon_from_truth, np.eye(4), atol=1e-6)
    point = np.array([[10.0, -20.0, 5.0]])                       # a truth point, where the reconstruction has it
    assert np.allclose(apply(se3.inverse(frame), point), apply(recon_from_truth, point), atol=1e-6)
