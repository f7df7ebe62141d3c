"""The shared two-thread pool."""

from __future__ import annotations

import threading

import pytest

from service.core.threads import side_by_side, two_threads


def test_two_threads_answers_in_order_and_runs_both_halves_at_once() -> None:
    """Each half waits for the other to start: one thread at a time would never finish."""
    both = threading.Barrier(2, timeout=10)

    def work(half: int) -> int:
        both.wait()
        return half + 10

    assert two_threads(work) == [10, 11]


def test_side_by_side_keeps_the_items_order_and_runs_two_at_a_time() -> None:
    """Items of uneven cost: the answers come in the items' order, and the first two run at once."""
    both = threading.Barrier(2, timeout=10)

    def work(item: int) -> int:
        if item < 2:
            both.wait()
        return item * item

    assert side_by_side(work, list(range(7))) == [0, 1, 4, 9, 16, 25, 36]
    assert side_by_side(work, []) == []


def test_an_error_in_either_half_reaches_the_caller() -> None:
    def work(half: int) -> int:
        if half == 1:
            raise ValueError("second half")
        return half

    with pytest.raises(ValueError, match="second half"):
        two_threads(work)


def test_work_in_the_pool_that_asks_the_pool_again_runs_inline() -> None:
    """Both pool threads busy with work that itself splits in two: it must not wait for itself."""
    def inner(half: int) -> int:
        return half

    assert two_threads(lambda outer: two_threads(inner)) == [[0, 1], [0, 1]]


def test_a_forked_child_gets_a_pool_of_its_own() -> None:
    """The parent's pool threads do not survive a fork (an RQ work horse): the child's work must
    still run, not wait for threads that are not there."""
    import multiprocessing

    assert two_threads(lambda half: half) == [0, 1]                  # the parent's pool has its threads
    ctx = multiprocessing.get_context("fork")
    answers = ctx.Queue()
    child = ctx.Process(target=lambda: answers.put(two_threads(lambda half: half * 2)))
    child.start()
    child.join(20)
    if child.is_alive():
        child.kill()
        pytest.fail("the forked child's work never ran")
    assert answers.get(timeout=5) == [0, 2] and child.exitcode == 0
