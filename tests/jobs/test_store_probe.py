"""The job store asked with a bound on the wait: a hung store is reported at once, a late answer is the
next probe's only while it is news, one question is in flight at a time."""

from __future__ import annotations

import threading
import time

import pytest

from service.jobs import store_probe
from service.jobs.store_probe import StoreProbe


def _answered(probe: StoreProbe) -> None:
    for _ in range(400):
        if probe._pending is not None and probe._pending.done():
            return
        time.sleep(0.01)
    raise AssertionError("the question was never answered")


def test_one_question_is_in_flight_and_its_late_answer_is_the_next_probe_s() -> None:
    release, asked = threading.Event(), []

    def ask() -> str:
        asked.append(1)
        release.wait(60)
        return "up"

    probe = StoreProbe(ask, wait_s=0.3)
    assert probe() is None and probe() is None and len(asked) == 1     # a hung store holds one question
    release.set()
    _answered(probe)
    assert probe() == "up" and len(asked) == 1                         # answered meanwhile: news
    assert probe() == "up" and len(asked) == 2                         # then the store is asked again


def test_a_late_answer_older_than_the_wait_is_thrown_away(monkeypatch: pytest.MonkeyPatch) -> None:
    """A store that answered 'up' slowly and failed since is seen failed, not up."""
    clock = [1000.0]
    monkeypatch.setattr(store_probe, "_now", lambda: clock[0])
    release, answers = threading.Event(), iter(["up", "down"])

    def ask() -> str:
        answer = next(answers)
        if answer == "up":
            release.wait(60)
        return answer

    probe = StoreProbe(ask, wait_s=0.3)
    assert probe() is None
    release.set()
    _answered(probe)
    clock[0] += 30.0                                                   # the next probe comes 30 s later
    assert probe() == "down"


def test_the_question_s_error_reaches_the_probe_and_the_next_probe_asks_again() -> None:
    calls = []

    def ask() -> bool:
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("the store's own error")
        return True

    probe = StoreProbe(ask, wait_s=5.0)
    with pytest.raises(RuntimeError, match="own error"):
        probe()
    assert probe() is True and len(calls) == 2
