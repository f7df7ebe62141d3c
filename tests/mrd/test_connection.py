"""The MRD connection's firm-up queue: ending one series neither waits for nor loses another's; a
series whose end drops a misplaced slice stays open for it."""

from __future__ import annotations

import json
import threading
import time
from concurrent.futures import ThreadPoolExecutor, wait

import ismrmrd
import pytest
from ismrmrd.serialization import ConfigText

from service.mrd import connection as mrd_connection
from service.mrd.connection import MrdConnection, SeriesState
from service.mrd.send import MrdLink, mrd_header
from tests.mrd.conftest import Case
from tests.support.firm_ups import GatedSession

CONFIG = ConfigText(json.dumps({"mc_samples": 10, "bias_correction": False}))


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
    monkeypatch.setattr(mrd_connection, "end_stack_messages", lambda answer: [{"type": "stack"}])
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


def _shifted(image: ismrmrd.Image, mm: float) -> ismrmrd.Image:
    """``image`` with its position moved ``mm`` along its slice direction (its pixels and the rest alike)."""
    moved = ismrmrd.Image(head=image.getHead(), data=image.data, meta=image.meta)
    moved.position = tuple(float(p) + mm * float(d) for p, d in zip(image.position, image.slice_dir))
    return moved


@pytest.mark.parametrize("sent_again", [True, False])
def test_a_series_whose_end_drops_a_misplaced_slice_stays_open_for_it(case: Case, serve, sent_again: bool) -> None:  # noqa: ANN001
    """Slice 2 taken 1 mm off its place before the series' slices agreed on their spacing: the
    series' end drops it and says so in the series' terms; the series stays the same stack, which
    ends once the slice comes again where it belongs, or at close without it (``not_received``)."""
    server = serve()
    client = MrdLink("127.0.0.1", server.port)
    images = case.images[0]
    client.send(CONFIG, mrd_header(slices=20), images[0], _shifted(images[2], 1.0),
                *[images[k] for k in range(20) if k not in (0, 2)], *([images[2]] if sent_again else []))
    received = client.close()
    messages = [json.loads(m) for m in received if isinstance(m, str)]
    (error,) = [m for m in messages if m["type"] == "error"]
    assert error["image_series_index"] == 0 and error["detail"].startswith(
        "series 0: the slices [2] lie off the even spacing of its other slices")
    (stack,) = [m for m in messages if m["type"] == "stack"]
    missing = [k for k, s in enumerate(stack["slices"]) if s["reason"] == "not_received"]
    assert stack["stack"] == "0" and len(stack["slices"]) == 20 and missing == ([] if sent_again else [2])
    assert messages[-1]["type"] == "summary" and messages[-1]["unfinished"] == {}


def test_a_series_ended_by_close_whose_end_drops_a_misplaced_slice_still_ends(case: Case, serve) -> None:  # noqa: ANN001
    """No slice count in the header: the series ends at CLOSE; its end drops the misplaced slice, and
    the stack then ends without it (``not_received``) rather than staying open with the summary's
    unfinished naming it."""
    server = serve()
    client = MrdLink("127.0.0.1", server.port)
    images = case.images[0]
    client.send(CONFIG, mrd_header(slices=None), images[0], _shifted(images[2], 1.0),
                *[images[k] for k in range(20) if k not in (0, 2)])
    received = client.close()
    messages = [json.loads(m) for m in received if isinstance(m, str)]
    (error,) = [m for m in messages if m["type"] == "error"]
    assert error["detail"].startswith("series 0: the slices [2] lie off the even spacing of its other slices")
    (stack,) = [m for m in messages if m["type"] == "stack"]
    missing = [k for k, s in enumerate(stack["slices"]) if s["reason"] == "not_received"]
    assert stack["stack"] == "0" and missing == [2]
    assert messages[-1]["type"] == "summary" and messages[-1]["unfinished"] == {}
