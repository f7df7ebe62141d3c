"""Where slices of different stacks cross: the lines, and the bounded point sets of the image term."""

from __future__ import annotations

import numpy as np

from service.consistency.intersections import pair_points
from service.geometry import se3
from service.geometry.pose import make_pose


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


def test_a_pass_keeps_whole_lines_within_its_point_budget(monkeypatch) -> None:  # noqa: ANN001
    import service.consistency.intersections as module

    monkeypatch.setattr(module, "MAX_POINTS", 100)
    stack = module.StackImages(np.ones((4, 8, 8), np.float32), np.ones((4, 8, 8), bool), (1.0, 1.0),
                               np.repeat(np.eye(4)[None], 4, 0), np.ones(4, bool))
    sampled = [module.SampledStack(stack, 1.0)] * 2
    pairs = np.array([[a, b] for a in range(4) for b in range(4, 8)])             # 16 pairs, 2 stacks
    term = module.ImageTerm(sampled, np.repeat([0, 1], 4), np.tile(np.arange(4), 2), pairs, np.arange(20.0))
    w = np.ones(len(term.pair_of))
    w[term.t_of >= 15] = 0.0                                                       # 15 points on each line
    term.select(w, min_weight=1.0)
    per_line = np.bincount(term.pair_of)
    assert per_line.sum() <= 100 and len(per_line) == 6 and np.all(per_line == 15)   # 6 whole lines of 15
    assert len(term.pairs) == 6 and set(map(tuple, term.pairs)) <= set(map(tuple, pairs))


def test_a_stack_cut_to_its_brain_samples_as_the_whole_slices_do(monkeypatch) -> None:  # noqa: ANN001
    """Cropping to the brain's box plus its margin (blocks of 2 x 2 fine pixels, an odd offset)
    changes no value or gradient the image term samples in and around the brain."""
    import service.consistency.intersections as module

    rng = np.random.default_rng(3)
    n, h, w = 3, 200, 180
    images = (1.0 + rng.random((n, h, w))).astype(np.float32)
    masks = np.zeros((n, h, w), bool)
    masks[:, 83:121, 61:110] = True
    stack = module.StackImages(images, masks, (0.5, 0.55), np.repeat(np.eye(4)[None], n, 0), np.ones(n, bool))
    cut = module.SampledStack(stack, 3.0)
    monkeypatch.setattr(module, "CROP_MARGIN_MM", 1e6)
    whole = module.SampledStack(stack, 3.0)
    assert cut.images.size < whole.images.size / 3
    inside = np.argwhere(masks[0])[::37]
    mm = np.column_stack([(inside[:, 1] - (w - 1) / 2) * 0.55, (inside[:, 0] - (h - 1) / 2) * 0.5,
                          np.zeros(len(inside)), np.ones(len(inside))])          # slice mm of brain pixels
    which = np.arange(len(inside)) % n
    rc_cut = (cut.pixel_from_slice @ mm.T).T
    rc_whole = (whole.pixel_from_slice @ mm.T).T
    assert np.allclose(cut.sample(which, rc_cut), whole.sample(which, rc_whole), atol=1e-5)
    assert np.allclose(cut.sample_gradient(which, rc_cut), whole.sample_gradient(which, rc_whole), atol=1e-5)
    assert np.allclose(cut.sample(which, rc_cut, masks=True), whole.sample(which, rc_whole, masks=True), atol=1e-6)
