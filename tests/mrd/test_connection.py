"""The MRD connection's firm-up queue: ending one series neither waits for nor loses another's."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor, wait

import pytest

from service.mrd import connection as mrd_connection
from service.mrd.connection import MrdConnection, SeriesState
from tests.support.firm_ups import GatedSession


def _connection(session: GatedSession) -> MrdConnection:
    conn = object.__new__(MrdConnection)                 # the queue alone: no socket, no ismrmrd streams
    conn.session, conn.refused_config = session, None
    conn.stage_lock, conn.send_lock = threading.Lock(), threading.Lock()
    conn.stage, conn.dirty, conn.firming = ThreadPoolExecutor(1), set(), None
    conn.series, conn.counts = {}, {"images": 0, "refused": 0, "stacks": 0}
    conn.sent = []
    conn.send_text = conn.sent.append
    return conn


def test_ending_a_series_keeps_the_firm_up_another_series_has_queued(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(mrd_connection, "stack_message", lambda answer: {"type": "stack"})
    session = GatedSession(held="0.1", stacks=("0.1", "1.1"))
    conn = _connection(session)
    conn.series = {0: SeriesState("0.1", {0, 1}), 1: SeriesState("1.1", {0})}
    conn.firm_up("0.1")                                  # running, held at the gate
    assert session.running.wait(5)
    conn.firm_up("1.1")                                  # queued behind it
    ending = threading.Thread(target=conn.end_series, args=(0,))
    ending.start()
    deadline = time.monotonic() + 10
    while conn.dirty and time.monotonic() < deadline:     # the end has taken the queue: then the gate opens
        time.sleep(0.001)
    session.gate.set()
    ending.join(10)
    if (queued := conn.firming) is not None:             # the queue run to its end
        wait([queued], timeout=10)
    assert ("end_stack", "0.1") in session.calls and conn.sent == [{"type": "stack"}]
    assert session.calls.count(("firm_up", "1.1")) == 1  # series 1's firm-up ran after series 0's end
    assert session.calls.index(("end_stack", "0.1")) < session.calls.index(("firm_up", "1.1"))
    conn.stage.shutdown()
