"""Each slice's expected error after the image refinement (service.consistency.refined_errors): the
Laplace spread against an explicit inverse, the stage's estimate against the images' spread."""

from __future__ import annotations

import numpy as np
import pytest

from service.consistency.refined_errors import (MAX_RELATIVE_MISMATCH, MISMATCH_POWER, REFINED_GAIN, SPREAD_GAIN,
                                                UNCHECKED_GAIN, expected_after, laplace_spread_mm)
from service.geometry.anchors import twist_spread_mm


def test_the_laplace_spread_reads_each_slices_block_of_the_inverse_hessian() -> None:
    """Against the explicit inverse of a random coupled Hessian (slices tied to each other, as
    crossing lines tie them): each slice's spread from its own 6 x 6 block, not a neighbour's."""
    rng = np.random.default_rng(2)
    root = rng.normal(size=(30, 30)) * np.tile([0.02, 0.02, 0.02, 1.0, 1.0, 1.0], 5)[None]
    hess = root.T @ root + np.diag(np.tile([400.0, 400.0, 400.0, 0.5, 0.5, 0.5], 5))
    inv = np.linalg.inv(hess)
    want = [float(twist_spread_mm(inv[6 * k:6 * k + 6, 6 * k:6 * k + 6])) for k in range(5)]
    np.testing.assert_allclose(laplace_spread_mm(hess), want, rtol=1e-8)
    assert len(set(np.round(want, 6))) == 5


def test_the_expected_error_after_refinement_meets_the_images_halfway() -> None:
    """The geometric mean of the stage's estimate and the images' spread where both exist; the stage's
    alone without a spread; a slice on no line keeps the unchecked gain."""
    out = expected_after([np.array([4.0, 4.0, 4.0])], [np.array([1.0, 1.0, np.nan])], [np.array([0.5, np.nan, 0.5])])[0]
    assert out[0] == pytest.approx(np.sqrt(REFINED_GAIN * 4.0 * SPREAD_GAIN * 0.5))
    assert out[1] == pytest.approx(REFINED_GAIN * 4.0) and out[2] == pytest.approx(UNCHECKED_GAIN * 4.0)


def test_the_stage_estimate_follows_the_mismatch_up_to_its_limit_only() -> None:
    """Below :data:`MAX_RELATIVE_MISMATCH` the stage's estimate grows in proportion to the mismatch;
    beyond it a slice is lost and every further mismatch gives the same estimate, with and without
    the images' spread."""
    cap = MAX_RELATIVE_MISMATCH
    m = np.array([0.5 * cap, cap, 2.0 * cap, 10.0 * cap])
    alone = expected_after([np.full(4, 3.0)], [m])[0]
    assert alone[:2] == pytest.approx(REFINED_GAIN * 3.0 * m[:2] ** MISMATCH_POWER)
    assert alone[2] == alone[3] == pytest.approx(alone[1])
    spread = expected_after([np.full(4, 3.0)], [m], [np.full(4, 1.5)])[0]
    assert spread[1] == pytest.approx(np.sqrt(2.0 ** MISMATCH_POWER) * spread[0])
    assert spread[3] == pytest.approx(spread[1])
