"""``/v1/stream`` end to end in the app: the messages of Stream v1, in order, with the simulated
truth; bad messages answered with an ``error`` while the session goes on; keys and limits."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from service.api import stream
from service.core.errors import InvalidParameter
from service.inference.registry import ModelRegistry
from service.streaming.frames import SliceFrame
from tests.api.conftest import make_client
from tests.support.firm_ups import GatedSession
from tests.support.streams import KeyedOracle, true_sent, two_stacks_case


@pytest.fixture(scope="module")
def case() -> tuple[KeyedOracle, list[list[SliceFrame]], list[np.ndarray]]:
    return two_stacks_case()


@pytest.fixture
def client(case) -> Iterator[TestClient]:  # noqa: ANN001
    with make_client(ModelRegistry({"default": case[0]}), stream_max_pixels=64 * 64) as c:
        yield c


def send_slice(ws, frame: SliceFrame, dtype: str = "float32", **override: object) -> None:  # noqa: ANN001
    msg = {"type": "slice", "stack": frame.stack, "index": frame.index, "shape": list(frame.pixels.shape),
           "dtype": dtype, "scanner_from_voxel": np.asarray(frame.scanner_from_voxel).tolist(), "mask": True, **override}
    ws.send_text(json.dumps(msg))
    ws.send_bytes(np.ascontiguousarray(frame.pixels, np.dtype(dtype).newbyteorder("<")).tobytes())
    if msg["mask"]:
        ws.send_bytes(np.ascontiguousarray(frame.mask, np.uint8).tobytes())


def receive(ws, kinds: tuple[str, ...] = ("pose",)) -> dict:  # noqa: ANN001
    """The next message of one of ``kinds`` (``update`` messages in between are kept aside)."""
    while True:
        msg = ws.receive_json()
        if msg["type"] in kinds:
            return msg
        assert msg["type"] == "update", msg


def test_a_session_answers_every_slice_in_order_where_the_truth_is(client, case) -> None:  # noqa: ANN001
    _, stacks, truths = case
    with client.websocket_connect("/v1/stream") as ws:
        ws.send_text(json.dumps({"type": "start", "mc_samples": 10, "bias_correction": False}))
        ready = ws.receive_json()
        assert ready["type"] == "ready" and ready["mc_samples"] == 10 and ready["model"]["name"] == "default"
        assert ready["localiser"] is True and ready["localiser_model"]["name"] == "default"    # the shipped one
        assert len(ready["localiser_model"]["sha256"]) == 64 and ready["localiser_model"]["version"]
        for frames, truth in zip(stacks, truths):
            for f in frames:
                send_slice(ws, f)
                pose = receive(ws)
                assert (pose["stack"], pose["index"]) == (f.stack, f.index)
                assert np.allclose(pose["atlas_from_voxel"], true_sent(truth, f.index), atol=1e-4)
                assert pose["latency_ms"] >= 0 and pose["localisation"]["method"] == "mask"
            ws.send_text(json.dumps({"type": "end_stack", "stack": frames[0].stack}))
            stack = receive(ws, ("stack",))
            assert [s["index"] for s in stack["slices"]] == list(range(len(frames)))
            assert all(s["stack"] == frames[0].stack and s["localisation"]["method"] == "mask" for s in stack["slices"])
            got = np.array([s["atlas_from_voxel"] for s in stack["slices"]])
            want = np.stack([true_sent(truth, k) for k in range(len(frames))])
            assert np.abs(got[:, :3, 3] - want[:, :3, 3]).max() < 0.5
            assert stack["consistency"]["acquisition_order"] == "as-streamed"
            assert 0.0 < stack["noise"]["input_noise"] < 0.06 and stack["noise"]["beyond_calibration"] is False
            assert stack["frame"]["expected_error_added_mm"] == 0.0 and "request_network_error_mm" in stack["frame"]
            assert 0.0 < stack["coverage"]["brain_fraction"] <= 1.0
            assert all(r["reason"] for r in stack["reacquire"])
            assert stack["judged_alone"] is (frames is stacks[0])          # the first stack had no other to cross it
        ws.send_text(json.dumps({"type": "end"}))
        summary = receive(ws, ("summary",))
        assert summary["stacks"] == ["ax", "cor"] and summary["slices"] == sum(len(f) for f in stacks)
        assert set(summary["reacquire"]) == {"ax", "cor"}                   # each stack's final list
        assert summary["unfinished"] == {}                                  # every stack ended
        assert summary["timing_ms"]["pose_latency_p95"] >= summary["timing_ms"]["pose_latency_p50"]
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
        assert closed.value.code == 1000


def test_a_stack_ends_without_a_slice_that_never_came_and_again_once_it_came(client, case) -> None:  # noqa: ANN001
    """The contract's ``stack`` lists every slice: one that never arrived has reason ``not_received``
    and is in ``reacquire``; sent after all, it reopens the stack, which ends again whole."""
    _, stacks, truths = case
    frames = stacks[0]
    with client.websocket_connect("/v1/stream") as ws:
        ws.send_text(json.dumps({"type": "start", "mc_samples": 10, "bias_correction": False}))
        ws.receive_json()
        for f in frames:
            if f.index != 5:
                send_slice(ws, f)
                receive(ws)
        ws.send_text(json.dumps({"type": "end_stack", "stack": "ax"}))
        stack = receive(ws, ("stack",))
        assert [s["index"] for s in stack["slices"] if s["reason"] == "not_received"] == [5]
        assert {"index": 5, "reason": "not_received"} in stack["reacquire"] and not stack["slices"][5]["accepted"]
        got = np.array([s["atlas_from_voxel"] for s in stack["slices"]])
        want = np.stack([true_sent(truths[0], k) for k in range(len(frames))])
        assert np.abs(np.delete(got - want, 5, axis=0)[:, :3, 3]).max() < 0.5
        send_slice(ws, frames[5])
        assert receive(ws)["index"] == 5
        ws.send_text(json.dumps({"type": "end_stack", "stack": "ax"}))
        again = receive(ws, ("stack",))
        assert not [s for s in again["slices"] if s["reason"] == "not_received"]
        assert np.abs(np.array(again["slices"][5]["atlas_from_voxel"])[:3, 3] - want[5, :3, 3]).max() < 0.5
        ws.send_text(json.dumps({"type": "end"}))
        summary = receive(ws, ("summary",))
        assert summary["unfinished"] == {} and {"index": 5, "reason": "not_received"} not in summary["reacquire"]["ax"]


def test_a_session_s_log_lines_carry_its_id_and_its_end_is_logged(client, case, caplog) -> None:  # noqa: ANN001
    """An operator follows one scanner's session through the log: its refusals and its end (slices
    answered, how long it ran) carry the ``session_id`` the client was given in ``ready``."""
    import logging
    _, stacks, _ = case
    with caplog.at_level(logging.INFO, logger="service"), client.websocket_connect("/v1/stream") as ws:
        ws.send_text(json.dumps({"type": "start", "mc_samples": 10, "bias_correction": False}))
        session_id = ws.receive_json()["session_id"]
        send_slice(ws, stacks[0][0])
        receive(ws)
        ws.send_text(json.dumps({"type": "dance"}))
        assert ws.receive_json()["type"] == "error"
        ws.send_text(json.dumps({"type": "end"}))
        assert receive(ws, ("summary",))["unfinished"] == {stacks[0][0].stack: {"missing": []}}    # never ended
    lines = {r.getMessage(): r for r in caplog.records if getattr(r, "session_id", None) == session_id}
    assert lines["stream message refused"].status == 400
    end = lines["stream session"]
    assert end.n_slices == 1 and end.duration_ms > 0 and end.route == "/v1/stream" and end.model == "default"


def test_a_pose_s_latency_runs_from_the_slice_s_last_frame(client, case, monkeypatch) -> None:  # noqa: ANN001
    """What the server does after the last frame counts (decoding the frames, waiting for a pose
    thread), not only the network's pass."""
    import time as clock

    import service.api.stream as stream_module

    def slow_frame(*args: object) -> SliceFrame:
        clock.sleep(0.2)
        return SliceFrame(*args)

    monkeypatch.setattr(stream_module, "SliceFrame", slow_frame)
    with client.websocket_connect("/v1/stream") as ws:
        ws.send_text(json.dumps({"type": "start", "mc_samples": 10, "bias_correction": False}))
        assert ws.receive_json()["type"] == "ready"
        send_slice(ws, case[1][0][0])
        assert receive(ws)["latency_ms"] >= 200


def test_bad_messages_get_an_error_naming_them_and_the_session_goes_on(client, case) -> None:  # noqa: ANN001
    _, stacks, truths = case
    f0, f1 = stacks[0][0], stacks[0][1]
    with client.websocket_connect("/v1/stream") as ws:
        send_slice(ws, f0)                                    # before start: one error, its two frames dropped
        assert "start message first" in ws.receive_json()["detail"]
        ws.send_text(json.dumps({"type": "start", "mc_samples": 0}))
        assert "start.mc_samples" in ws.receive_json()["detail"]
        ws.send_text(json.dumps({"type": "start", "mc_samples": 10, "variance_threshold": 10 ** 400}))
        assert "start.variance_threshold: a positive number" in ws.receive_json()["detail"]      # not a 500
        ws.send_text(json.dumps({"type": "start", "mc_samples": 10, "variance_treshold": 40}))   # misspelt: named
        assert "unknown options ['variance_treshold']" in ws.receive_json()["detail"]
        ws.send_text(json.dumps({"type": "start", "mc_samples": 10, "bias_correction": False}))
        assert ws.receive_json()["type"] == "ready"
        cases = [
            ("not json", None, "not JSON"),
            (json.dumps([1, 2]), None, "JSON object"),
            ("[" * 5000 + "]" * 5000, None, "nested too deeply"),
            (json.dumps({"type": "dance"}), None, "unknown message type"),
            (json.dumps({"type": "slice", "stack": "ax", "index": 1, "shape": [4, 4, 4], "dtype": "uint8",
                         "scanner_from_voxel": np.eye(4).tolist()}), None, "slice.shape"),
            (json.dumps({"type": "slice", "stack": "ax", "index": 1, "shape": [True, 4], "dtype": "uint8",
                         "scanner_from_voxel": np.eye(4).tolist()}), None, "slice.shape"),      # a bool is no count
            (json.dumps({"type": "slice", "stack": "ax", "index": 1, "shape": [100, 100], "dtype": "uint8",
                         "scanner_from_voxel": np.eye(4).tolist()}), None, "limit of 4096 pixels"),
            (json.dumps({"type": "slice", "stack": "ax", "index": 1, "shape": [4, 4], "dtype": "float64",
                         "scanner_from_voxel": np.eye(4).tolist()}), None, "slice.dtype"),
            (json.dumps({"type": "slice", "stack": "ax", "index": 1, "shape": [4, 4], "dtype": "uint8",
                         "scanner_from_voxel": np.eye(4).tolist()}), b"\x00" * 15, "15 bytes, 16 were due"),
            (json.dumps({"type": "slice", "stack": "ax", "index": 1, "shape": [4, 4], "dtype": "uint8",
                         "scanner_from_voxel": [["1", 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}), None,
             "slice.scanner_from_voxel"),                                         # text, though numpy reads it
            (json.dumps({"type": "slice", "stack": "ax", "index": 1, "shape": [4, 4], "dtype": "uint8",
                         "scanner_from_voxel": [[True, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}), None,
             "slice.scanner_from_voxel"),
            (json.dumps({"type": "slice", "stack": "ax", "index": 1, "shape": [4, 4], "dtype": "uint8", "maks": True,
                         "scanner_from_voxel": np.eye(4).tolist()}), b"\x00" * 16, "slice: unknown fields ['maks']"),
            (json.dumps({"type": "end_stack", "stack": "ax", "foo": 1}), None, "end_stack: unknown fields ['foo']"),
            (json.dumps({"type": "end", "now": True}), None, "end: unknown fields ['now']"),    # the session stays
            (json.dumps({"type": "end_stack", "stack": "nothing"}), None, "no slice"),
            (json.dumps({"type": "end_stack", "stack": "ax\u202e\r\nevil"}), None,      # echoed in every answer
             "end_stack.stack: control, format or line-separator characters are not allowed"),
        ]
        for text, data, words in cases:
            ws.send_text(text)
            if data is not None:
                ws.send_bytes(data)
            err = ws.receive_json()
            assert err["type"] == "error" and err["status"] == 400 and words in err["detail"], (words, err)
        send_slice(ws, f0, stack="a\u202eb")                  # a refused header with mask: one error, not three
        assert "slice.stack" in ws.receive_json()["detail"]
        send_slice(ws, f0, mask="true")                       # a wrong mask value, its two frames: one error
        assert "slice.mask" in ws.receive_json()["detail"]
        ws.send_text(json.dumps({"type": "ping"}))
        assert ws.receive_json() == {"type": "pong"}
        ws.send_bytes(b"\x01\x02")                            # a binary frame out of place
        assert "not expected" in ws.receive_json()["detail"]
        huge = f0.scanner_from_voxel.tolist()
        huge[0][3] = 10 ** 400                                # a refused header's frames: one error, not three
        send_slice(ws, f0, scanner_from_voxel=huge)
        err = ws.receive_json()
        assert err["status"] == 400 and "scanner_from_voxel" in err["detail"], err
        header = {"type": "slice", "stack": "ax", "index": 0, "shape": list(f0.pixels.shape), "dtype": "float32",
                  "scanner_from_voxel": f0.scanner_from_voxel.tolist()}
        pixels, mask = f0.pixels.astype("<f4").tobytes(), f0.mask.astype(np.uint8).tobytes()
        for text, frames in ((json.dumps({**header, "maks": True}), [pixels, mask]),   # a misspelt mask: two frames
                             (json.dumps({**header, "mask": True, "note": "x" * 70_000}), [pixels, mask]),
                             (json.dumps({**header, "mask": True}), [json.dumps(f0.pixels.tolist()), mask])):
            ws.send_text(text)                                # each gets one error and its frames no other
            for frame in frames:
                ws.send_text(frame) if isinstance(frame, str) else ws.send_bytes(frame)
            ws.send_text(json.dumps({"type": "ping"}))
            assert ws.receive_json()["type"] == "error" and ws.receive_json() == {"type": "pong"}
        send_slice(ws, f0, dtype="uint16")                    # another dtype; the session still works
        pose = receive(ws)
        assert pose["index"] == 0
        send_slice(ws, f1, scanner_from_voxel=stacks[1][1].scanner_from_voxel.tolist())
        assert "axes differ" in receive(ws, ("error",))["detail"]
        send_slice(ws, f1, scanner_from_voxel=f0.scanner_from_voxel.tolist())     # its index, not its place
        assert "slice 1 sits where slice 0" in receive(ws, ("error",))["detail"]
        ws.send_text(json.dumps({"type": "end_stack", "stack": "ax"}))
        assert "lacks" not in json.dumps(receive(ws, ("stack", "error")))


def test_plain_http_to_the_stream_is_told_to_upgrade(client) -> None:  # noqa: ANN001
    """A GET, HEAD, OPTIONS or POST to the stream's route is no missing route: 426 naming the WebSocket."""
    for method in ("GET", "HEAD", "OPTIONS", "POST"):
        r = client.request(method, "/v1/stream")
        assert r.status_code == 426 and r.headers["upgrade"] == "websocket", (method, r.status_code)
        assert method == "HEAD" or "a WebSocket; connect with ws://" in r.json()["detail"]


def test_keys_and_the_session_limit(case) -> None:  # noqa: ANN001
    registry = ModelRegistry({"default": case[0]})
    with make_client(registry, api_keys="k1", stream_max_sessions=1) as client:
        for wrong in ("wrong", "café", "\ud800x"):                          # a lone surrogate too: 401, not a 1006
            with client.websocket_connect("/v1/stream") as ws:
                ws.send_text(json.dumps({"type": "auth", "api_key": wrong}))
                assert ws.receive_json()["status"] == 401
                with pytest.raises(WebSocketDisconnect) as closed:
                    ws.receive_json()
                assert closed.value.code == 1008
        with client.websocket_connect("/v1/stream", headers={"X-API-Key": "k1"}) as first:
            first.send_text(json.dumps({"type": "start", "mc_samples": 5}))
            assert first.receive_json()["type"] == "ready"
            with client.websocket_connect("/v1/stream") as second:
                second.send_text(json.dumps({"type": "auth", "api_key": "k1"}))
                busy = second.receive_json()
                assert busy["status"] == 503 and busy["retry_after_s"] >= 1
                with pytest.raises(WebSocketDisconnect) as closed:
                    second.receive_json()
                assert closed.value.code == 1013


def test_another_site_s_page_cannot_open_a_session_without_keys(case) -> None:  # noqa: ANN001
    with make_client(ModelRegistry({"default": case[0]})) as client:
        with pytest.raises(WebSocketDisconnect) as refused:
            with client.websocket_connect("/v1/stream", headers={"Origin": "https://evil.example"}):
                pass
        assert refused.value.code == 1008                  # closed before the handshake: an HTTP 403
        with client.websocket_connect("/v1/stream", headers={"Host": "localhost:8000",
                                                             "Origin": "http://localhost:8000"}) as ws:
            ws.send_text(json.dumps({"type": "start", "mc_samples": 5}))
            assert ws.receive_json()["type"] == "ready"


def test_a_site_without_a_default_localiser_streams_slices_that_bring_their_masks(case) -> None:  # noqa: ANN001
    """A server whose only localiser has another name starts sessions without one (``localiser``
    false): it refused every session, masks or not, naming the missing ``default``."""
    from service.preprocess.localise import Localisers

    with make_client(ModelRegistry({"default": case[0]})) as client:
        client.app.state.localisers = Localisers({"fetal-v2": object()})
        with client.websocket_connect("/v1/stream") as ws:
            ws.send_text(json.dumps({"type": "start", "mc_samples": 5}))
            ready = ws.receive_json()
            assert ready["type"] == "ready" and ready["localiser"] is False, ready


def test_a_start_that_fails_takes_no_session_slot(case, monkeypatch) -> None:  # noqa: ANN001
    """A start refused after the slots were counted (here: its session cannot be made) answers an
    error each time it is sent, and the slots are all free once the client goes: retries do not
    hold slots for good."""
    from service.api import stream
    from service.core.errors import InvalidParameter

    def refused(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise InvalidParameter("start: refused by the test")

    monkeypatch.setattr(stream, "StreamSession", refused)
    with make_client(ModelRegistry({"default": case[0]}), stream_max_sessions=3) as client:
        with client.websocket_connect("/v1/stream") as ws:
            for _ in range(3):
                ws.send_text(json.dumps({"type": "start", "mc_samples": 5}))
                error = ws.receive_json()
                assert error["type"] == "error" and "refused by the test" in error["detail"]
                assert client.app.state.stream_sessions == 0
        assert client.app.state.stream_sessions == 0


def test_a_session_slot_is_taken_by_a_start_and_a_connection_that_never_starts_is_closed(case, monkeypatch) -> None:  # noqa: ANN001
    """One session slot: a connection that says nothing holds none (another starts its session
    beside it) and is closed going away after the start deadline; a start while the slot is taken
    is refused with 503 and 1013; the slot is free again when the session ends."""
    from service.api import stream

    monkeypatch.setattr(stream, "START_TIMEOUT_S", 5.0)
    with make_client(ModelRegistry({"default": case[0]}), stream_max_sessions=1) as client:
        with client.websocket_connect("/v1/stream") as silent:
            with client.websocket_connect("/v1/stream") as first:
                first.send_text(json.dumps({"type": "start", "mc_samples": 5}))
                assert first.receive_json()["type"] == "ready"
                silent.send_text(json.dumps({"type": "start", "mc_samples": 5}))
                busy = silent.receive_json()
                assert busy["status"] == 503 and busy["retry_after_s"] >= 1
                with pytest.raises(WebSocketDisconnect) as closed:
                    silent.receive_json()
                assert closed.value.code == 1013
                first.send_text(json.dumps({"type": "end"}))
                assert first.receive_json()["type"] == "summary"
        assert client.app.state.stream_sessions == 0
        monkeypatch.setattr(stream, "START_TIMEOUT_S", 0.5)
        with client.websocket_connect("/v1/stream") as chatty:                # auth again and again, no start
            t0 = time.perf_counter()
            for _ in range(10):
                chatty.send_text(json.dumps({"type": "auth"}))
                time.sleep(0.2)
                if time.perf_counter() - t0 > 0.6:
                    break
            error = chatty.receive_json()
            assert error["status"] == 408 and "idle for 0.5 s" in error["detail"]
        with client.websocket_connect("/v1/stream") as idle:                  # never starts: closed
            error = idle.receive_json()
            assert error["status"] == 408 and "idle for 0.5 s" in error["detail"]
            with pytest.raises(WebSocketDisconnect) as closed:
                idle.receive_json()
            assert closed.value.code == 1001


def test_refused_messages_do_not_keep_a_session_open(case) -> None:  # noqa: ANN001
    """A client that sends only messages the server refuses is idle: closed after ``stream_idle_s``
    however often it sends them, slices whose header is right and whose frame is not among them."""
    f0 = case[1][0][0]
    header = json.dumps({"type": "slice", "stack": "ax", "index": 0, "shape": list(f0.pixels.shape),
                         "dtype": "float32", "scanner_from_voxel": f0.scanner_from_voxel.tolist()})
    with make_client(ModelRegistry({"default": case[0]}), stream_idle_s=0.6, stream_max_pixels=64 * 64) as client:
        with client.websocket_connect("/v1/stream") as ws:
            ws.send_text(json.dumps({"type": "start", "mc_samples": 5}))
            assert ws.receive_json()["type"] == "ready"
            for k in range(20):
                if k % 2:
                    ws.send_text(header)
                    ws.send_bytes(b"\x00" * 8)
                else:
                    ws.send_text("garbage{")
                answer = ws.receive_json()
                if answer["status"] == 408:
                    break
                assert answer["status"] == 400
                time.sleep(0.1)
            assert answer["status"] == 408          # within the 20 refusals' 2 s and more, over 3 x the idle limit
            with pytest.raises(WebSocketDisconnect) as closed:
                ws.receive_json()
            assert closed.value.code == 1001


def test_a_connection_that_does_not_authenticate_in_time_is_closed(case, monkeypatch) -> None:  # noqa: ANN001
    from service.api import stream

    monkeypatch.setattr(stream, "AUTH_TIMEOUT_S", 0.2)
    with make_client(ModelRegistry({"default": case[0]}), api_keys="k1") as client:
        with client.websocket_connect("/v1/stream") as ws:                  # says nothing
            assert ws.receive_json()["status"] == 401
            with pytest.raises(WebSocketDisconnect) as closed:
                ws.receive_json()
            assert closed.value.code == 1008


def test_an_idle_session_is_told_so_and_closed_going_away(case) -> None:  # noqa: ANN001
    with make_client(ModelRegistry({"default": case[0]}), stream_idle_s=0.3) as client:
        with client.websocket_connect("/v1/stream") as ws:
            ws.send_text(json.dumps({"type": "start", "mc_samples": 5}))
            assert ws.receive_json()["type"] == "ready"
            error = ws.receive_json()                                 # nothing sent for 0.3 s
            assert error["type"] == "error" and error["status"] == 408 and "idle for 0.3 s" in error["detail"]
            assert error["problem_type"] == "/problems/request-timeout"
            with pytest.raises(WebSocketDisconnect) as closed:
                ws.receive_json()
            assert closed.value.code == 1001


def test_a_ping_and_a_slice_s_header_are_signs_of_life(case) -> None:  # noqa: ANN001
    """Between stacks a script pings (each answered ``pong``) and the session outlives its idle limit;
    a slice whose frames come late after its header is answered, not cut off."""
    _, stacks, _ = case
    f0 = stacks[0][0]
    with make_client(ModelRegistry({"default": case[0]}), stream_idle_s=0.5, stream_max_pixels=64 * 64) as client:
        with client.websocket_connect("/v1/stream") as ws:
            ws.send_text(json.dumps({"type": "start", "mc_samples": 5}))
            assert ws.receive_json()["type"] == "ready"
            for _ in range(5):                                # 1.5 s in all, three times the limit
                time.sleep(0.3)
                ws.send_text(json.dumps({"type": "ping"}))
                assert ws.receive_json() == {"type": "pong"}
            time.sleep(0.3)
            ws.send_text(json.dumps({"type": "slice", "stack": "ax", "index": 0, "shape": list(f0.pixels.shape),
                                     "dtype": "float32", "scanner_from_voxel": f0.scanner_from_voxel.tolist(),
                                     "mask": True}))
            time.sleep(0.35)                                  # 0.65 s since the last pong, 0.35 since the header
            ws.send_bytes(f0.pixels.astype("<f4").tobytes())
            ws.send_bytes(f0.mask.astype(np.uint8).tobytes())
            assert receive(ws)["index"] == 0
            ws.send_text(json.dumps({"type": "ping", "now": 1}))
            assert "ping: unknown fields ['now']" in ws.receive_json()["detail"]


def test_auth_after_start_is_refused_and_keeps_no_session_alive(case) -> None:  # noqa: ANN001
    """An ``auth`` once the session has started gets an ``error``, and, as a refused message, does not
    count as a sign of life: the idle limit still closes a session that sends nothing else (an auth
    every 0.2 s kept a session of a 0.5 s limit open, unanswered, for ever)."""
    with make_client(ModelRegistry({"default": case[0]}), stream_idle_s=0.5) as client:
        with client.websocket_connect("/v1/stream") as ws:
            ws.send_text(json.dumps({"type": "start", "mc_samples": 5}))
            assert ws.receive_json()["type"] == "ready"
            for _ in range(3):
                ws.send_text(json.dumps({"type": "auth", "api_key": "k"}))
                time.sleep(0.2)
            answers = [ws.receive_json() for _ in range(4)]
            assert [a["status"] for a in answers] == [400, 400, 400, 408]
            assert all(a["detail"].startswith("auth:") for a in answers[:3])


def test_ending_a_stack_keeps_the_firm_up_another_stack_has_queued(monkeypatch: pytest.MonkeyPatch) -> None:
    """One stack's end waits for the running firm-up only; another stack's queued one runs after it,
    and an end the session refuses changes nothing: the queued firm-up still runs."""
    monkeypatch.setattr(stream, "end_stack_messages", lambda answer: [{"type": "stack"}])
    session = GatedSession(held="a", stacks=("a", "b"))
    conn = object.__new__(stream.StreamConnection)         # the queue alone: no socket
    conn.session, conn.dirty, conn.firming, conn.sent = session, set(), None, []
    conn.stages = {"firm_up": ThreadPoolExecutor(1), "end_stack": ThreadPoolExecutor(1)}

    async def send(message: dict) -> None:
        conn.sent.append(message)

    conn.send = send

    async def scenario(end: str) -> None:
        session.gate.clear()
        session.running.clear()
        conn.firm_up("a")                                    # running, held at the gate
        assert await asyncio.to_thread(session.running.wait, 5)
        conn.firm_up("b")                                    # queued behind it
        ending = asyncio.create_task(conn.end_stack(end))
        while conn.dirty:                                    # the end has taken the queue: then the gate opens
            await asyncio.sleep(0.001)
        session.gate.set()
        try:
            await ending
        finally:
            await asyncio.gather(conn.firming, return_exceptions=True)   # the queue run to its end

    asyncio.run(scenario("a"))
    assert conn.sent == [{"type": "stack"}] and session.calls.count(("firm_up", "b")) == 1
    assert session.calls.index(("end_stack", "a")) < session.calls.index(("firm_up", "b"))
    with pytest.raises(InvalidParameter):
        asyncio.run(scenario("no-such-stack"))               # refused: b's queued firm-up still runs
    assert session.calls.count(("firm_up", "b")) == 2
    for pool in conn.stages.values():
        pool.shutdown()


def test_a_client_gone_while_an_answer_is_sent_ends_its_session_quietly(monkeypatch, caplog) -> None:  # noqa: ANN001
    """A scanner that closes right after ``end_stack``: the send of the stack's answer, or of a
    background firm-up's update, finds the socket gone (Starlette's WebSocketDisconnected). That is
    a session's normal end: no error logged, nothing raised out of the app, the firm-up queue
    dropped; a receive after the disconnect ends the session alike."""
    import logging
    from types import SimpleNamespace

    from starlette.websockets import WebSocketDisconnected

    class GoneSocket:
        app = SimpleNamespace(state=SimpleNamespace(settings=SimpleNamespace(stream_ping_timeout_s=60.0),
                                                    registry=None, localisers=None, metrics=None,
                                                    stream_pose_limiter=None,
                                                    stream_stages={"firm_up": ThreadPoolExecutor(1)}, stream_sessions=0))

        async def send_text(self, text: str) -> None:
            raise WebSocketDisconnected('Cannot call "send" once a close message has been sent.')

        async def receive(self) -> dict:
            raise WebSocketDisconnected('Cannot call "receive" once a disconnect message has been received.')

    conn = stream.StreamConnection(GoneSocket())                              # type: ignore[arg-type]
    with pytest.raises(stream._Closed):
        asyncio.run(conn.send({"type": "stack"}))
    monkeypatch.setattr(stream, "update_messages", lambda updates: [{"type": "update"}])
    conn.session = SimpleNamespace(firm_up=lambda stack: ["an update"])
    conn.dirty = {"ax", "cor"}
    conn.settings = SimpleNamespace(stream_idle_s=30.0, stream_ping_timeout_s=60.0)
    with caplog.at_level(logging.INFO, logger="service"):
        asyncio.run(conn._firm_up_loop())
        asyncio.run(conn.run())                                               # returns: the client has gone
    assert not conn.dirty
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], [r.getMessage() for r in caplog.records]


def test_a_client_that_stops_reading_ends_its_session_instead_of_holding_its_slot() -> None:
    """A client that sends and never reads fills the connection's buffers and every send waits on it:
    without a deadline the session, its memory and its slot were held for as long as the client kept
    the socket open (neither the pings nor the idle limit ended it). Each send, and each one queued
    behind it, now gives up after ``stream_ping_timeout_s`` as a client gone."""
    from types import SimpleNamespace

    from service.core.settings import Settings

    class StuckSocket:
        async def send_text(self, text: str) -> None:
            await asyncio.Event().wait()                 # a buffer that never drains

    state = SimpleNamespace(settings=Settings(stream_ping_timeout_s=0.3), registry=None, localisers=None,
                            stream_pose_limiter=None, stream_stages={}, metrics=None)
    ws = StuckSocket()
    ws.app = SimpleNamespace(state=state)
    conn = stream.StreamConnection(ws)

    async def two_sends() -> list[str]:
        outcomes = await asyncio.gather(conn.send({"type": "pose"}), conn.send({"type": "stack"}),
                                        return_exceptions=True)
        return [type(o).__name__ for o in outcomes]

    t = time.perf_counter()
    assert asyncio.run(two_sends()) == ["_Closed", "_Closed"]
    assert time.perf_counter() - t < 3.0                  # each within its deadline, not for ever
