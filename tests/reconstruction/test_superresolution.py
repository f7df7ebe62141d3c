"""Super-resolution: its operators are what the normal equations need (adjoint pairs, a symmetric
positive semi-definite prior), and from the true poses it recovers the phantom better than the
Gaussian average it starts from."""

from __future__ import annotations

import numpy as np
import pytest

from service.reconstruction.forward import ForwardModel
from service.reconstruction.gaussian_average import gaussian_average
from service.reconstruction.grid import bounds_of, make_grid
from service.reconstruction.superresolution import (_diff, _diff_adjoint, default_delta, edge_weights, regulariser,
                                                    solve_without, super_resolve)
from tests.reconstruction.helpers import psnr_ncc, reference_on


def _inner(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.dot(a.ravel().astype(np.float64), b.ravel().astype(np.float64)))


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_the_difference_and_its_adjoint_are_adjoint(axis: int, rng: np.random.Generator) -> None:
    x = rng.normal(size=(7, 6, 5))
    y = _diff(rng.normal(size=(7, 6, 5)), axis)                 # zero on the last plane, as D's range is
    assert _inner(_diff(x, axis), y) == pytest.approx(_inner(x, _diff_adjoint(y, axis)), rel=1e-12)


def test_the_prior_is_symmetric_and_positive_semidefinite(rng: np.random.Generator) -> None:
    x, z = rng.normal(size=(2, 8, 7, 6))
    omega = edge_weights(rng.normal(size=(8, 7, 6)) * 5.0, delta=1.0).astype(np.float64)
    assert _inner(regulariser(x, omega), z) == pytest.approx(_inner(x, regulariser(z, omega)), rel=1e-10)
    assert _inner(x, regulariser(x, omega)) > 0
    assert np.allclose(regulariser(np.full((8, 7, 6), 3.0), omega), 0.0)     # a constant volume costs nothing


def test_super_resolution_from_the_true_poses_beats_the_average_it_starts_from(acquisition) -> None:  # noqa: ANN001
    """Measured (seed 0, 1 mm grid, 8 iterations): 28.8 dB / NCC 0.966 -> 40.9 dB / 0.998; the mean
    miss of the left-out stack's pixels 1.61 with it, 1.97 without it. Thresholds leave room."""
    ss = acquisition.slice_set()
    grid = make_grid(1.0, bounds_of(ss.positions(), 5.0))
    ref, mask = reference_on(grid, acquisition)
    start = gaussian_average(ss, ss.atlas_from_voxel, grid)
    model = ForwardModel(ss, ss.atlas_from_voxel, grid, psf_points=5)
    weights = np.ones(ss.n_pixels, np.float32)
    out = super_resolve(model, ss.values, weights, start.volume, iterations=8, support=start.support)
    before, after = psnr_ncc(start.volume, ref, mask), psnr_ncc(out.volume, ref, mask)
    assert after[0] > before[0] + 6.0 and after[1] > 0.99
    assert out.residual_norms[-1] < out.residual_norms[0]
    assert out.volume.min() >= 0 and not np.any(out.volume[~start.support])
    # leaving a stack's pixels out: the other two stacks alone predict its slices less well
    left_out = ss.stack_index[ss.slice_id] == 0
    assert 0 < left_out.sum() < ss.n_pixels
    without = solve_without(model, ss.values, weights, left_out, out.volume, iterations=8, lam=0.1,
                            delta=default_delta(out.volume, start.support), support=start.support)
    miss = lambda v: float(np.abs(model.forward(v)[left_out] - ss.values[left_out]).mean())  # noqa: E731
    assert miss(without) > miss(out.volume)
