"""The acquisition order a request gives: parsed, checked against its stack, and used by the stage."""

from __future__ import annotations

import numpy as np
import pytest

from service.consistency import fit_stack
from service.consistency.slice_order import (
    GIVEN,
    NAMED_ORDERS,
    SliceOrder,
    acquisition_orders,
    per_stack,
)
from service.geometry import se3
from service.geometry.anchors import ed
from tests.consistency.test_stack_fit import NOISE, stack


@pytest.mark.parametrize("n", [1, 2, 7, 8, 23])
def test_every_named_order_acquires_each_slice_once(n: int) -> None:
    for name, t in acquisition_orders(n).items():
        assert sorted(t.tolist()) == list(range(n)), name
    even = acquisition_orders(n)["interleaved-even-first"]
    assert (np.diff(even[::2]) == 1).all() and (even[::2] < (n + 1) // 2).all()      # even slices first, in turn


def test_words_and_sequences_are_parsed_and_wrong_ones_named() -> None:
    assert SliceOrder.parse("AUTO").names == NAMED_ORDERS
    assert SliceOrder.parse("interleaved").names == ("interleaved-even-first", "interleaved-odd-first")
    assert SliceOrder.parse(" 2, 0,1 ").sequence == (2, 0, 1)
    assert SliceOrder.parse("2,0,1").times(3)[GIVEN].tolist() == [1, 2, 0]        # slice 2 first, then 0, then 1
    for text in ("zigzag", "0;1;2", "", "1.5,0", "x" * 30_000):
        with pytest.raises(ValueError):
            SliceOrder.parse(text)
    for seq, n in (("0,1,2", 4), ("0,1,1,2", 4), ("1,2,3,4", 4), ("-1,0,1,2", 4)):
        with pytest.raises(ValueError, match="once"):
            SliceOrder.parse(seq).times(n)


def test_one_order_serves_every_stack_and_counts_must_match() -> None:
    seq = SliceOrder.parse("sequential")
    assert per_stack(None, 3) == [SliceOrder()] * 3
    assert per_stack([seq], 3) == [seq] * 3
    assert per_stack([seq, SliceOrder()], 2)[1].names == NAMED_ORDERS
    with pytest.raises(ValueError, match="2 values for 3 stacks"):
        per_stack([seq, seq], 3)


def test_the_stage_keeps_to_the_order_it_was_given() -> None:
    rng = np.random.default_rng(11)
    truth, nk = stack(rng, "moderate", n=40)
    poses = truth @ se3.exp(rng.normal(0, 1, (len(truth), 6)) * NOISE * 0.2)
    given = SliceOrder.parse(",".join(str(k) for k in np.argsort(acquisition_orders(40)["interleaved-even-first"])))
    fit = fit_stack(poses, nk, expected_error_mm=np.full(40, 3.0), times=given.times(40))
    assert fit.acquisition_order == GIVEN and np.isfinite(fit.bandwidth)
    wrong = fit_stack(poses, nk, expected_error_mm=np.full(40, 3.0), times=SliceOrder.parse("sequential").times(40))
    assert wrong.acquisition_order == "sequential"
    assert ed(fit.poses, truth).mean() < 0.8 * ed(wrong.poses, truth).mean()     # the true order follows the motion


def test_told_interleaved_the_stage_no_longer_takes_smooth_network_errors_for_motion() -> None:
    # Mild motion over an interleaved acquisition; network errors that change smoothly with depth
    # (neighbouring slices look alike) and exceed what the slices' spreads say: over the sequential
    # order they look like motion, and the likelihood takes it.
    rng = np.random.default_rng(3)
    auto, told, chosen = [], [], []
    for _ in range(6):
        truth, nk = stack(rng, "mild", n=30)
        depth = np.linspace(0, 1, 30)[:, None]
        smooth = np.sin(2 * np.pi * (depth * rng.uniform(0.5, 1.0, 6) + rng.uniform(0, 1, 6)))
        errors = (2.0 * smooth + 0.5 * rng.normal(0, 1, (30, 6))) * NOISE
        poses = truth @ se3.exp(errors)
        kept = fit_stack(poses, nk, expected_error_mm=np.full(30, 10.0))
        auto.append(ed(kept.poses, truth).mean())
        chosen.append(kept.acquisition_order)
        told.append(ed(fit_stack(poses, nk, expected_error_mm=np.full(30, 10.0),
                                 times=SliceOrder.parse("interleaved").times(30)).poses, truth).mean())
    assert chosen.count("sequential") >= 4
    assert np.mean(told) < 0.7 * np.mean(auto)


def test_the_schema_pattern_admits_what_parse_reads() -> None:
    import re

    from service.consistency.slice_order import PATTERN

    for text in ("auto", " interleaved ", "sequential", "interleaved-odd-first", "0, 2,1", "12,3"):
        assert re.match(PATTERN, text) and SliceOrder.parse(text) is not None, text
    for text in ("zigzag", "", "1.5,0", "0;1", "-1,0", "1" * 7, "0,,1"):
        assert not re.match(PATTERN, text), text
