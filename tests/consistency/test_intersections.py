"""Where slices of different stacks cross: the lines, and the bounded point sets of the image term."""

from __future__ import annotations

import numpy as np
import pytest

from service.consistency.intersections import ImageTerm, candidate_pairs, lines, pair_points
from service.consistency.slice_images import SampledStack, StackImages
from service.geometry import se3
from service.geometry.pose import make_pose
from tests.consistency.conftest import disturbed


def test_line_points_lie_on_both_planes() -> None:
    rng = np.random.default_rng(0)
    a = make_pose(se3.so3_exp(rng.normal(0, 1, (4, 3))), rng.normal(0, 10, (4, 3)))
    b = make_pose(se3.so3_exp(rng.normal(0, 1, (4, 3))), rng.normal(0, 10, (4, 3)))
    t = np.linspace(-20, 20, 9)
    pts = pair_points(a, b, np.array([[0, 1], [2, 3], [3, 0]]), t)
    for (i, j), p in zip([(0, 1), (2, 3), (3, 0)], pts):
        for pose in (a[i], b[j]):                                 # distance to each plane ~ 0
            assert np.abs((p - pose[:3, 3]) @ pose[:3, 2]).max() < 1e-9
        assert np.allclose(np.linalg.norm(np.diff(p, axis=0), axis=1), 5.0)      # evenly spaced along the line


def test_the_lines_closed_form_inverse_and_nearest_point_against_simulated_planes() -> None:
    """Random slice poses (planes from 30 to 90 degrees apart, as candidate pairs are): ``inv`` is the
    inverse of the rows ``na, nb, d``, and ``p`` lies on both planes, nearest the origins' midpoint
    of all the line's points (the line moved along itself by 1 mm is further from it)."""
    rng = np.random.default_rng(4)
    poses = se3.exp(np.concatenate([rng.normal(0, 1.0, (40, 3)), rng.normal(0, 20.0, (40, 3))], axis=1))
    pairs = candidate_pairs(poses, np.arange(40) % 2, np.ones(40, bool))
    assert len(pairs) > 50
    ln = lines(poses, poses, pairs)
    rows = np.stack([ln.na, ln.nb, ln.d], axis=1)
    np.testing.assert_allclose(rows @ ln.inv, np.broadcast_to(np.eye(3), rows.shape), atol=1e-9)
    on_a = np.einsum("mi,mi->m", ln.na, ln.p - ln.oa)
    on_b = np.einsum("mi,mi->m", ln.nb, ln.p - ln.ob)
    np.testing.assert_allclose(np.stack([on_a, on_b]), 0.0, atol=1e-9)
    here = np.linalg.norm(ln.p - ln.m, axis=1)
    for shift in (-1.0, 1.0):
        assert (np.linalg.norm(ln.p + shift * ln.d - ln.m, axis=1) > here).all()


def test_a_pass_keeps_whole_lines_within_its_point_budget(monkeypatch) -> None:  # noqa: ANN001
    import service.consistency.intersections as module

    monkeypatch.setattr(module, "MAX_POINTS", 100)
    stack = StackImages(np.ones((4, 8, 8), np.float32), np.ones((4, 8, 8), bool), (1.0, 1.0),
                        np.repeat(np.eye(4)[None], 4, 0), np.ones(4, bool))
    sampled = [SampledStack(stack, 1.0)] * 2
    pairs = np.array([[a, b] for a in range(4) for b in range(4, 8)])             # 16 pairs, 2 stacks
    term = module.ImageTerm(sampled, np.repeat([0, 1], 4), np.tile(np.arange(4), 2), pairs, np.arange(20.0))
    w = np.ones(len(term.pair_of))
    w[term.t_of >= 15] = 0.0                                                       # 15 points on each line
    term.select(w, min_weight=1.0)
    per_line = np.bincount(term.pair_of)
    assert per_line.sum() <= 100 and len(per_line) == 6 and np.all(per_line == 15)   # 6 whole lines of 15
    assert len(term.pairs) == 6 and set(map(frozenset, term.pairs)) <= set(map(frozenset, pairs))   # either slice first


@pytest.mark.parametrize("budget", [500, 3_000, 10**6])
def test_points_chosen_in_the_masks_are_those_every_points_weight_chooses(acquisition, budget: int) -> None:  # noqa: ANN001
    """A term made at the poses holds only the points inside both slices' mask boxes, and
    ``select_in_masks`` samples the masks of only the pairs the budget reaches; together they keep
    exactly the points :meth:`select` keeps from every point's mask weight (the same pairs, points
    and weights), at a budget that binds hard, one that binds a little, and none."""
    images, truth = acquisition
    poses = np.concatenate(disturbed(truth, 3.0, 3.0, seed=2))
    stack_of = np.repeat(np.arange(3), [len(t) for t in truth])
    local = np.concatenate([np.arange(len(t)) for t in truth])
    atlas = poses @ se3.inverse(np.concatenate([s.slice_from_network for s in images]))
    pairs = candidate_pairs(atlas, stack_of, np.ones(len(poses), bool))
    sampled = [SampledStack(s, 3.0) for s in images]
    every = ImageTerm(sampled, stack_of, local, pairs, np.arange(-70.0, 70.1, 2.0))
    every.select(np.clip(np.prod(every.values(atlas, masks=True), axis=0), 0, 1).astype(float), 1.0, budget)
    chosen = ImageTerm(sampled, stack_of, local, pairs, np.arange(-70.0, 70.1, 2.0), atlas)
    assert len(chosen.pair_of) < 0.8 * len(np.arange(-70.0, 70.1, 2.0)) * len(pairs)        # the boxes leave points out
    chosen.select_in_masks(atlas, 1.0, budget)
    assert 0 < len(chosen.pair_of) <= budget
    assert np.array_equal(chosen.pairs, every.pairs) and np.array_equal(chosen.pair_of, every.pair_of)
    assert np.array_equal(chosen.t_of, every.t_of) and np.allclose(chosen.sw, every.sw)
    assert np.array_equal(chosen.residuals(atlas), every.residuals(atlas))
