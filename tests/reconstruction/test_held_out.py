"""The held-out scores a job reads, and the stacks it leaves out because the others do not predict them."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from service.reconstruction.held_out import coherence_score, held_out_score, stack_held_out, stacks_apart, without_stacks_apart


def test_scores_are_read_whole_per_stack_and_with_one_stack_from_alternate_slices() -> None:
    """A job of one stack has no leave-one-stack-out score: its coherence is the alternate slices'."""
    r = SimpleNamespace(quality={"leave_one_stack_out": {"median_ncc": 0.7, "per_stack_median_ncc": [0.9, 0.5]}})
    assert held_out_score(r) == coherence_score(r) == 0.7
    assert stack_held_out(r, np.array([3, 3, 7])).tolist() == [0.9, 0.9, 0.5]
    assert stack_held_out(r, np.array([0, 1, 2])) is None                          # the scores of other stacks
    one = SimpleNamespace(quality={"leave_one_stack_out": {"median_ncc": None, "per_stack_median_ncc": [None]},
                                   "leave_alternate_slices_out": {"median_ncc": 0.62}})
    assert held_out_score(one) is None and coherence_score(one) == 0.62 and stack_held_out(one, np.array([0])) is None
    assert held_out_score(SimpleNamespace(quality=None)) is None


def test_a_stack_is_apart_only_where_two_others_agree() -> None:
    r = SimpleNamespace(quality={"leave_one_stack_out": {"per_stack_median_ncc": [0.9, 0.3, 0.35]}})
    assert stacks_apart(r, np.array([0, 1, 2])) == []                 # one stack agrees: none can be the odd one


def test_a_stack_the_others_do_not_predict_is_left_out_only_where_the_volume_without_it_holds() -> None:
    """Stack 2 apart from the two others: the volume is made again without its slices, and kept
    where its stacks predict each other; a volume again incoherent, or a job of two stacks (neither
    the odd one), keeps the first."""
    from dataclasses import dataclass
    from types import SimpleNamespace

    @dataclass
    class Slices:
        stack_index: np.ndarray
        include: np.ndarray

    def result(per: list, median: float) -> SimpleNamespace:
        return SimpleNamespace(quality={"leave_one_stack_out": {"median_ncc": median, "per_stack_median_ncc": per}})

    asked: list = []
    slices = Slices(np.array([0, 0, 1, 1, 2, 2]), np.array([1, 1, 1, 0, 1, 1], bool))
    first = result([0.9, 0.86, 0.41], 0.8)
    good = without_stacks_apart(slices, first, lambda kept, named: asked.append((kept, named)) or
                                result([0.9, 0.87, None], 0.88))
    assert good.quality["stacks_left_out"] == [2] and asked[0][1] == "2"
    assert asked[0][0].include.tolist() == [True, True, True, False, False, False]
    assert without_stacks_apart(slices, first, lambda kept, named: result([0.3, 0.4, None], 0.35)) is first
    two = Slices(np.array([0, 1]), np.ones(2, bool))
    assert without_stacks_apart(two, result([0.9, 0.41], 0.6), lambda *a: pytest.fail("made again")) \
        is not None
