"""Twin-aware MC statistics: a split between the twins neither inflates the variance nor hides."""

from __future__ import annotations

import numpy as np
import pytest

from service.geometry import anchors, encodings, se3, twin
from service.inference.estimator import slice_statistics, statistics


def cloud(rng: np.random.Generator, n_slices: int, n_mc: int, on_twin: float) -> tuple[np.ndarray, np.ndarray]:
    truth = se3.exp(np.concatenate([rng.normal(0, 1.0, (n_slices, 3)), rng.normal(0, 15, (n_slices, 3))], 1))
    samples = truth[:, None] @ se3.exp(rng.normal(0, 1, (n_slices, n_mc, 6)) * [0.03, 0.03, 0.03, 1, 1, 1])
    flip = np.zeros((n_slices, n_mc), bool)
    flip[:, : int(round(on_twin * n_mc))] = True
    samples = np.where(flip[..., None, None], twin.twin(samples, 0.7), samples)
    return truth, samples


@pytest.mark.parametrize("on_twin", [0.0, 0.3, 0.45])
def test_samples_split_between_twins_keep_a_small_variance_and_report_the_split(on_twin: float) -> None:
    rng = np.random.default_rng(0)
    truth, samples = cloud(rng, 40, 100, on_twin)
    est = statistics(anchors.encode(samples), "anchor", 0.7)
    assert np.allclose(est.twin_mass, on_twin)
    assert est.variance.max() < 10.0                        # ~ 2 * 3 * 0.03^2 + 3 mm^2, not hundreds
    assert np.abs(est.mean[:, :3, 3] - truth[:, :3, 3]).max() < 1.0
    _, naive = se3.frechet_mean_and_variance(samples)
    if on_twin > 0:
        assert np.median(naive) > 50.0                      # what a twin-blind mean would report


def test_the_majority_branch_wins_and_the_spread_is_in_mm() -> None:
    rng = np.random.default_rng(1)
    truth, samples = cloud(rng, 10, 100, 0.7)               # 70 % on the twin: the twin is the answer
    est = statistics(anchors.encode(samples), "anchor", 0.7)
    assert np.allclose(est.twin_mass, 0.3)
    tw = twin.twin(truth, 0.7)
    assert np.abs(est.mean[:, :3, 3] - tw[:, :3, 3]).max() < 1.0
    assert np.all((est.spread_mm > 1.0) & (est.spread_mm < 4.0))


def test_a_request_reduced_in_two_halves_equals_it_reduced_whole() -> None:
    """:func:`statistics` splits the slices between two threads: every field equals the one-thread
    reduction's, slice for slice (41 slices: halves of 20 and 21)."""
    from service.inference.estimator import slice_statistics

    rng = np.random.default_rng(2)
    _, samples = cloud(rng, 41, 50, 0.2)
    labels = anchors.encode(samples)
    both, whole = statistics(labels, "anchor", 0.7), slice_statistics(labels, "anchor", 0.7)
    for name in ("mean", "variance", "degenerate", "twin_mass", "spread_mm"):
        assert np.array_equal(getattr(both, name), getattr(whole, name)), name


def test_one_sample_has_no_measured_variance_and_no_slice_is_accepted_on_it() -> None:
    """mc_samples = 1: a spread of 0 would accept poses tens of mm off; the variance is unknown (NaN),
    which the accept flags judge as high_variance, and the pose itself is still given."""
    from service.inference import acceptance

    rng = np.random.default_rng(2)
    truth, samples = cloud(rng, 5, 1, 0.0)
    est = statistics(anchors.encode(samples), "anchor", 0.7)
    assert np.isnan(est.variance).all() and np.isfinite(est.spread_mm).all()
    assert np.allclose(est.mean, samples[:, 0], atol=1e-6)
    flags = acceptance.reasons(np.ones(5), np.zeros(5, bool), np.zeros((5, 3)), est.variance, 1e9)
    assert flags == ["high_variance"] * 5
    two = statistics(anchors.encode(cloud(rng, 5, 2, 0.0)[1]), "anchor", 0.7)
    assert np.isfinite(two.variance).all()


@pytest.mark.parametrize("label_type", ["anchor", "grid"])
def test_a_non_finite_sample_makes_its_slice_degenerate_not_its_stack_undecidable(label_type: str) -> None:
    """One NaN sample in one slice: that slice may not vote (degenerate) and its statistics are those
    of its finite samples (a grid label decodes NaN to the identity pose, which would be averaged
    in); the other slices are as without it."""
    rng = np.random.default_rng(4)
    poses = se3.exp(np.array([0.3, 0.1, 0.2, 25.0, 4.0, 10.0])) @ se3.exp(rng.normal(0, 0.02, (3, 20, 6)))
    lab = encodings.encode(label_type, poses)
    clean = slice_statistics(lab, label_type)
    lab[1, 7] = np.nan
    broken = slice_statistics(lab, label_type)
    assert broken.degenerate.tolist() == [False, True, False] and not clean.degenerate.any()
    assert np.isfinite(broken.mean).all() and np.isfinite(broken.variance).all()
    np.testing.assert_allclose(broken.mean[[0, 2]], clean.mean[[0, 2]])
    alone = slice_statistics(np.delete(lab[1:2], 7, axis=1), label_type)      # its 19 finite samples
    np.testing.assert_allclose(broken.mean[1], alone.mean[0], atol=1e-9)
    np.testing.assert_allclose([broken.variance[1], broken.spread_mm[1]], [alone.variance[0], alone.spread_mm[0]])
    lab[0, 1:] = np.nan                                  # one finite sample: no spread measured
    lab[2] = np.nan                                      # none: no variance, no spread
    worse = slice_statistics(lab, label_type)
    assert worse.degenerate.tolist() == [True, True, True]
    assert np.isnan(worse.variance[[0, 2]]).all() and np.isnan(worse.spread_mm[2]) and not worse.estimated[2]
