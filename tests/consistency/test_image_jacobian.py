"""The image term's derivatives by each slice's pose: against finite differences, and the normal
equations assembled pair by pair against the sparse products."""

from __future__ import annotations

import numpy as np

from service.consistency.image_jacobian import PointJacobian, image_jacobian
from service.consistency.intersections import ImageTerm, candidate_pairs
from service.consistency.slice_images import SampledStack
from service.geometry import se3
from tests.consistency.conftest import disturbed


def test_the_analytic_jacobian_agrees_with_finite_differences(acquisition) -> None:  # noqa: ANN001
    """The residuals' derivatives by each slice's twist, composed from the moving line and the image
    gradients, against forward differences of the residuals themselves (3 mm smoothing: where the
    bilinear images are smooth enough that both measure the same thing). A wrong sign or frame
    would be off by 100 % or more; the gradient images differ from the differences of the bilinear
    interpolant by about 9 % (median; 15 % at the 95th percentile). The in-plane rotation moves the
    points only along the lines, where both images change alike: small columns, larger relative
    differences, so left out of the bound."""
    images, truth = acquisition
    poses = np.concatenate(disturbed(truth, 2.0, 2.0, seed=1))
    stack_of = np.repeat(np.arange(3), [len(t) for t in truth])
    local = np.concatenate([np.arange(len(t)) for t in truth])
    network_from_slice = se3.inverse(np.concatenate([s.slice_from_network for s in images]))
    free = np.concatenate([s.masks.reshape(len(s.masks), -1).sum(1) for s in images]) >= 20
    col = -np.ones(len(poses), int)
    col[free] = np.arange(free.sum())
    atlas = poses @ network_from_slice
    pairs = candidate_pairs(atlas, stack_of, free)
    term = ImageTerm([SampledStack(s, 3.0) for s in images], stack_of, local, pairs, np.arange(-60.0, 60.1, 2.0))
    term.select(np.clip(np.prod(term.values(atlas, masks=True), axis=0), 0, 1).astype(float), 1.0)

    def residual(params: np.ndarray) -> np.ndarray:
        twist = np.zeros((len(poses), 6))
        twist[free] = params
        return term.residuals(poses @ se3.exp(twist) @ network_from_slice) / 0.15

    x = np.zeros((int(free.sum()), 6))
    r0 = residual(x)
    steps = np.array([5e-3, 5e-3, 5e-3, 0.2, 0.2, 0.2])      # rad, mm: forward differences, one column at a time
    differences = np.zeros((len(r0), x.size))
    for c in range(x.size):
        dx = np.zeros(x.size)
        dx[c] = steps[c % 6]
        differences[:, c] = (residual(dx.reshape(x.shape)) - r0) / steps[c % 6]
    analytic = image_jacobian(term, atlas, poses, col, 0.15).sparse().toarray()
    columns = np.flatnonzero((np.arange(analytic.shape[1]) % 6 != 2) & (np.abs(differences).sum(0) > 0))
    error = np.linalg.norm(analytic[:, columns] - differences[:, columns], axis=0) / np.linalg.norm(differences[:, columns], axis=0)
    assert np.median(error) < 0.12 and np.percentile(error, 95) < 0.25, (np.median(error), np.percentile(error, 95))
    assert np.count_nonzero(analytic[:, np.abs(differences).sum(0) == 0]) == 0


def test_the_normal_equations_assembled_pair_by_pair_equal_the_sparse_products() -> None:
    """``J^T W J`` and ``J^T W r`` from each pair's blocks, against the sparse Jacobian's products,
    with pairs of several points, single points, and slices that keep their poses (column -1)."""
    rng = np.random.default_rng(7)
    counts = rng.integers(1, 9, 40)
    pair_of = np.repeat(np.arange(len(counts)), counts)
    place = np.concatenate([rng.permutation(12)[:c] for c in counts])         # places along a line, gaps between
    slices = rng.integers(-1, 12, (len(counts), 2))
    slices[:, 1] = np.where(slices[:, 1] == slices[:, 0], (slices[:, 0] + 1) % 12, slices[:, 1])
    jac = PointJacobian.of_points(rng.normal(size=(len(pair_of), 2, 6)), slices, pair_of, place, 72)
    w, r = rng.uniform(0.1, 1.0, len(pair_of)), rng.normal(size=len(pair_of))
    hess, grad = jac.normal(w, r)
    dense = jac.sparse().toarray()
    np.testing.assert_allclose(hess, dense.T @ (w[:, None] * dense), atol=1e-10)
    np.testing.assert_allclose(grad, dense.T @ (w * r), atol=1e-10)
    assert not dense[:, :6][(slices[pair_of] == 0).sum(1) == 0].any()         # slice 0's columns: its pairs only
