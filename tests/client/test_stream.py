"""``svrnet stream``: the order the slices go out in, the session against a scripted WebSocket server
(errors shown, the stream going on, exit codes), and end to end against a real ``svrnet-server`` with
the shipped model. The slices a stack file is cut into: ``test_scanner_stack.py``."""

from __future__ import annotations

import json
import socket
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from typer.testing import CliRunner
from websockets.sync.server import ServerConnection, serve

import client.cli as cli
import client.exits as exits
import client.stream as streaming
from client.stream import send_order

runner = CliRunner(env={"COLUMNS": "200"})


# --- (a) the order the slices are sent in ------------------------------------------------------------------


def test_send_orders() -> None:
    assert send_order(6, "interleaved") == [0, 2, 4, 1, 3, 5] and send_order(1, "interleaved") == [0]
    assert send_order(6, "interleaved-odd-first") == [1, 3, 5, 0, 2, 4] and send_order(3, "1, 0,2") == [1, 0, 2]
    for bad in ("random", "0,1", "0,1,1", "0,1,3"):                 # not a word, nor each slice once
        with pytest.raises(ValueError, match="order"):
            send_order(3, bad)


# --- (b) against a scripted server: the messages, the table, errors and exit codes ---------------------------


@pytest.fixture
def stack_file(tmp_path: Path) -> Path:
    path = tmp_path / "ax.nii.gz"
    nib.save(nib.Nifti1Image(np.random.default_rng(0).random((6, 5, 4)).astype(np.float32),
                             np.diag([1.0, 1.0, 3.0, 1.0])), path)
    return path


@contextmanager
def scripted_server(handler: Callable[[ServerConnection], None], **options: object) -> Iterator[str]:
    """A WebSocket server on a free port running ``handler`` per connection; yields its http:// address."""
    with serve(handler, "127.0.0.1", 0, **options) as server:
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        try:
            yield f"http://127.0.0.1:{server.socket.getsockname()[1]}"
        finally:
            server.shutdown()
            thread.join(timeout=5)


def pose(msg: dict, **fields: object) -> dict:
    return {"type": "pose", "stack": msg["stack"], "index": msg["index"], "accepted": True, "reason": None,
            "expected_error_mm": 2.0, "translation_mm": [1.0, 2.0, float(msg["index"])], "latency_ms": 12.0, **fields}


def test_a_scripted_session_shows_poses_updates_errors_and_the_summary(stack_file: Path, tmp_path: Path) -> None:
    heard: list[tuple[dict, list[bytes]]] = []
    keys: list[str | None] = []

    def handler(ws: ServerConnection) -> None:
        keys.append(ws.request.headers.get("Authorization"))
        start = json.loads(ws.recv())
        assert start["mc_samples"] == 10 and start["masks_hold_csf"] is True and "bias_correction" not in start
        ws.send(json.dumps({"type": "ready", "session_id": "s1", "model": {"name": "default", "version": "1"},
                            "mc_samples": 10, "max_expected_error_mm": 5.0,
                            "limits": {"slices": 100, "pixels_per_slice": 1000, "idle_s": 30}}))
        while True:
            msg = json.loads(ws.recv())
            frames = [ws.recv() for _ in range(1 + bool(msg.get("mask")))] if msg["type"] == "slice" else []
            heard.append((msg, frames))
            if msg["type"] == "slice" and (msg["stack"], msg["index"]) == ("ax", 1):
                ws.send(json.dumps({"type": "error", "problem_type": "/problems/invalid-parameter",
                                    "title": "Invalid parameter", "status": 400, "detail": "slice: made up"}))
            elif msg["type"] == "slice":
                rejected = (msg["stack"], msg["index"]) == ("ax", 3)
                reason = "high_expected_error" if rejected else None
                ws.send(json.dumps(pose(msg, accepted=not rejected, reason=reason)))
            elif msg["type"] == "end_stack":                  # cor moves a slice of ax, ended before it
                moved = {"stack": "ax", "index": 0 if msg["stack"] == "ax" else 2}
                now = {} if msg["stack"] == "ax" else {"reacquire": []}      # ax's list once cor crossed it
                ws.send(json.dumps({"type": "update", "stack": "ax", "slices": [pose(moved, expected_error_mm=1.5)],
                                    **now}))
                final = (0, 2) if msg["stack"] == "ax" else (0, 1, 2, 3)
                ws.send(json.dumps({"type": "stack", "stack": msg["stack"],
                                    "slices": [pose({"stack": msg["stack"], "index": k},
                                                    **({"accepted": False, "reason": "empty"} if k == 1 and len(final) == 4
                                                       else {})) for k in final],
                                    "reacquire": [{"index": 3, "reason": "high_expected_error"}] if len(final) < 4
                                    else [], "judged_alone": msg["stack"] == "ax",
                                    "coverage": {"brain_fraction": 0.42, "gaps": [{"extent_mm": 9.0}]}}))
            elif msg["type"] == "end":
                ws.send(json.dumps({"type": "summary", "stacks": ["ax", "cor"], "slices": 7,
                                    "coverage": {"brain_fraction": 0.42, "gaps": []},
                                    "unfinished": {"sag": {"missing": [4, 7]}},
                                    "timing_ms": {"pose_latency_p50": 12.0, "pose_latency_p95": 19.0}}))
                ws.close(1000)
                return

    cor = tmp_path / "cor.nii.gz"
    cor.write_bytes(stack_file.read_bytes())
    out = tmp_path / "messages.jsonl"
    with scripted_server(handler) as url:
        result = runner.invoke(cli.app, ["stream", str(stack_file), str(cor), "--server", url, "--api-key", "k1",
                                         "--slice-order", "interleaved-even-first", "--slice-order", "3,2,1,0",
                                         "--mc-samples", "10", "--masks-hold-csf", "--json-out", str(out)])
    assert result.exit_code == exits.EXIT_BAD_INPUT, result.output        # a stack without final poses (sag)
    assert keys == ["Bearer k1"]
    slices = [(m, f) for m, f in heard if m["type"] == "slice"]
    assert [(m["stack"], m["index"]) for m, _ in slices] == [("ax", 0), ("ax", 2), ("ax", 1), ("ax", 3),
                                                            ("cor", 3), ("cor", 2), ("cor", 1), ("cor", 0)]
    assert [m["acquisition_index"] for m, _ in slices] == [0, 1, 2, 3] * 2
    assert all(m["dtype"] == "float32" and m["shape"] == [6, 5] and len(f) == 1 and len(f[0]) == 6 * 5 * 4
               for m, f in slices)
    assert [m["type"] for m, _ in heard if m["type"] != "slice"] == ["end_stack", "end_stack", "end"]
    text = " ".join(result.output.split())
    assert "error (slice ax #1): 400 Invalid parameter: slice: made up" in text
    assert "✗ high_expected_error" in text and "updated" in text
    assert ("stack ax: 2 of 2 slices with brain accepted (judged alone: the next stack that crosses it can accept its slices) · reacquire: "
            "high_expected_error #3 · coverage 42% of the brain, 1 gap") in text
    assert "stack ax now: 2 of 3 slices with brain accepted · reacquire: none" in text and "stack cor now" not in text   # #1 got an error
    assert "update of stack ax: #2 ✓ 1.5 mm" in text and "stack cor: 3 of 3 slices with brain accepted · reacquire: none" in text
    assert ("session: 2 stack(s), 7 slices · pose latency p50 12 ms, p95 19 ms · "
            "coverage 42% of the brain, 0 gaps") in text
    assert "stack sag: no final poses, slices 4, 7 never arrived" in text      # a stack the summary says did not end
    kinds = [json.loads(line)["type"] for line in out.read_text().splitlines()]
    assert kinds == ["ready", "pose", "pose", "error", "pose", "update", "stack", "pose", "pose", "pose", "pose",
                     "update", "stack", "summary"]


@pytest.mark.parametrize(("answer", "code"), [
    ({"type": "error", "title": "Service saturated", "status": 503, "detail": "32 stream sessions are open",
      "retry_after_s": 2}, 1013),
    ({"type": "error", "title": "Unauthorized", "status": 401, "detail": "missing or invalid API key"}, 1008),
], ids=["busy-1013", "unauthorized-1008"])
def test_a_refused_session_exits_with_the_clients_codes(stack_file: Path, answer: dict, code: int) -> None:
    def handler(ws: ServerConnection) -> None:
        ws.recv()
        ws.send(json.dumps(answer))
        ws.close(code)

    with scripted_server(handler) as url:
        result = runner.invoke(cli.app, ["stream", str(stack_file), "--server", url])
        keyed = runner.invoke(cli.app, ["stream", str(stack_file), "--server", url, "--api-key", "wrong"])
    assert result.exit_code == {1013: exits.EXIT_BUSY, 1008: exits.EXIT_UNAUTHORIZED}[code], result.output
    assert answer["detail"] in " ".join(result.output.split())
    if code == 1008:                                   # a key was refused, or none was given: the hint says which
        assert "give the key with" in " ".join(result.output.split())
        assert "the key sent was refused" in " ".join(keyed.output.split()), keyed.output


def test_a_handshake_refused_as_a_wrong_path_names_the_address_not_the_key(stack_file: Path) -> None:
    """A server answers a WebSocket at a path it does not serve with 403 before the handshake (the
    key is checked after it): the client says to check the address, not the key."""
    def refuse(connection: ServerConnection, request: object) -> object:
        return connection.respond(403, "Forbidden")

    with scripted_server(lambda ws: None, process_request=refuse) as url:
        result = runner.invoke(cli.app, ["stream", str(stack_file), "--server", url + "/v1"])
    said = " ".join(result.output.split())
    assert result.exit_code == exits.EXIT_CONNECTION, result.output
    assert "/v1/v1/stream" in said and "server's root" in said and "key" not in said


def test_no_server_exits_with_connection_failed_and_keeps_an_earlier_record(stack_file: Path, tmp_path: Path) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    record = tmp_path / "earlier.jsonl"
    record.write_text('{"type": "ready"}\n')
    result = runner.invoke(cli.app, ["stream", str(stack_file), "--server", f"http://127.0.0.1:{port}",
                                     "--json-out", str(record)])
    assert result.exit_code == exits.EXIT_USAGE and "exists; nothing was sent (--overwrite" in result.output
    result = runner.invoke(cli.app, ["stream", str(stack_file), "--server", f"http://127.0.0.1:{port}",
                                     "--json-out", str(record), "--overwrite"])
    assert result.exit_code == exits.EXIT_CONNECTION and "cannot open ws://127.0.0.1" in result.output
    assert record.read_text() == '{"type": "ready"}\n'                 # no session, the last one's record kept


def test_a_server_restart_mid_session_says_so_and_keeps_what_was_answered(stack_file: Path) -> None:
    """A server that restarts (close code 1012) after answering two slices: the poses received stay
    in the output (the live table is transient), and the error says to stream the stacks again."""
    def handler(ws: ServerConnection) -> None:
        ws.recv()
        ws.send(json.dumps({"type": "ready", "session_id": "s1", "model": {"name": "default"}, "mc_samples": 10}))
        for _ in range(2):
            msg = json.loads(ws.recv())
            ws.recv()
            ws.send(json.dumps(pose(msg)))
        ws.close(1012, "service restart")

    with scripted_server(handler) as url:
        result = runner.invoke(cli.app, ["stream", str(stack_file), "--server", url])
    text = " ".join(result.output.split())
    assert result.exit_code == exits.EXIT_CONNECTION and "the server is restarting (close code 1012" in text, text
    assert "received before the session ended" in text and "stream the stacks again" in text


def test_a_server_that_answers_no_json_is_a_server_error(stack_file: Path) -> None:
    def handler(ws: ServerConnection) -> None:
        ws.recv()
        ws.send("<html>502 Bad Gateway</html>")
        ws.close(1000)

    with scripted_server(handler) as url:
        result = runner.invoke(cli.app, ["stream", str(stack_file), "--server", url])
    assert result.exit_code == exits.EXIT_SERVER and "no JSON" in result.output, result.output


@pytest.mark.parametrize(("answer", "code"), [("rejected", exits.EXIT_NOTHING_USABLE), ("refused", exits.EXIT_BAD_INPUT)])
def test_a_session_with_nothing_accepted_exits_as_predict_would(stack_file: Path, answer: str, code: int) -> None:
    """No slice accepted in the stack's final answer: 12, as ``svrnet predict``; every slice refused: 5."""
    def handler(ws: ServerConnection) -> None:
        json.loads(ws.recv())
        ws.send(json.dumps({"type": "ready", "session_id": "s1", "model": {"name": "default", "version": "1"},
                            "mc_samples": 10, "limits": {"slices": 100, "pixels_per_slice": 1000, "idle_s": 30}}))
        posed = []
        while True:
            msg = json.loads(ws.recv())
            if msg["type"] == "slice":
                [ws.recv() for _ in range(1 + bool(msg.get("mask")))]
                if answer == "refused":
                    ws.send(json.dumps({"type": "error", "title": "Invalid parameter", "status": 400, "detail": "no"}))
                else:
                    posed.append(pose(msg, accepted=False, reason="high_expected_error"))
                    ws.send(json.dumps(posed[-1]))
            elif msg["type"] == "end_stack":
                ws.send(json.dumps({"type": "stack", "stack": msg["stack"], "slices": posed, "reacquire": [],
                                    "coverage": {"brain_fraction": 0.1, "gaps": []}}) if posed else
                        json.dumps({"type": "error", "title": "Invalid parameter", "status": 400, "detail": "no slice"}))
            elif msg["type"] == "end":
                ws.send(json.dumps({"type": "summary", "stacks": ["ax"], "slices": len(posed), "timing_ms": {}}))
                ws.close(1000)
                return

    with scripted_server(handler) as url:
        result = runner.invoke(cli.app, ["stream", str(stack_file), "--server", url])
    assert result.exit_code == code, result.output


def test_a_session_that_fills_up_stops_sending_and_names_what_it_could_not_take(stack_file: Path,
                                                                                tmp_path: Path) -> None:
    """The server takes three slices, then refuses for a full session: the client sends no further slice
    once the refusal is in
    and no end_stack of a stack none of whose slices was taken, ends the stack it began, names the
    slices left, and exits 5; too many stacks for the session are refused before any slice is sent."""
    second = tmp_path / "co.nii.gz"
    second.write_bytes(stack_file.read_bytes())
    received: list[dict] = []

    def handler(ws: ServerConnection) -> None:
        json.loads(ws.recv())
        ws.send(json.dumps({"type": "ready", "session_id": "s1", "model": {"name": "default", "version": "1"},
                            "mc_samples": 10, "limits": {"slices": 100, "stacks": 4, "pixels_per_slice": 1000,
                                                         "session_mb": 1.0, "idle_s": 30}}))
        posed: list[dict] = []
        while True:
            msg = json.loads(ws.recv())
            received.append(msg)
            if msg["type"] == "slice":
                ws.recv()
                if len(posed) < 3:
                    posed.append(pose(msg))
                    ws.send(json.dumps(posed[-1]))
                else:
                    ws.send(json.dumps({"type": "error", "problem_type": "/problems/session-full", "status": 400,
                                        "title": "Session full", "detail": "slice: a session keeps at most 1 MB"}))
            elif msg["type"] == "end_stack":
                ws.send(json.dumps({"type": "stack", "stack": msg["stack"], "slices": posed, "reacquire": [],
                                    "coverage": {"brain_fraction": 0.1, "gaps": []}}))
            elif msg["type"] == "end":
                ws.send(json.dumps({"type": "summary", "stacks": ["ax"], "slices": 3, "timing_ms": {}}))
                ws.close(1000)
                return

    with scripted_server(handler) as url:
        result = runner.invoke(cli.app, ["stream", str(stack_file), str(second), "--server", url], env={"COLUMNS": "200"})
    assert result.exit_code == exits.EXIT_BAD_INPUT, result.output
    assert "stack ax: slices 3 not posed" in result.output and "stack co: slices 0, 1, 2, 3 not posed" in result.output
    sent = [(m["type"], m.get("stack")) for m in received]
    assert sent.count(("slice", "ax")) == 4                     # once the refusal is in, nothing more is sent:
    assert sent.count(("slice", "co")) < streaming.MAX_IN_FLIGHT    # at most what was on its way before it came
    assert ("end_stack", "ax") in sent and ("end_stack", "co") not in sent and sent[-1] == ("end", None)
    with scripted_server(handler) as url:
        result = runner.invoke(cli.app, ["stream", *[str(stack_file)] * 5, "--server", url])
    assert result.exit_code == exits.EXIT_BAD_INPUT and "5 stacks: over the server's limit of 4" in result.output


def test_a_pace_the_server_would_close_the_session_at_is_refused_before_any_slice() -> None:
    """``--pace`` at or over the server's ``ready.limits.idle_s`` would have the session closed between
    two slices: refused before any is sent; a server that states no limit takes any pace."""
    from client.errors import UnusableInput

    with pytest.raises(UnusableInput, match="a slice every 300 s: the server closes a session idle for 300 s"):
        streaming._check_limits([], {"idle_s": 300}, 300.0)
    streaming._check_limits([], {"idle_s": 300}, 299.0)
    streaming._check_limits([], {}, 1e6)                       # a server that says no limit


# --- (c) end to end: a real svrnet-server with the shipped model ---------------------------------------------------


def phantom_stack(directory: Path, name: str, slice_axis: int) -> tuple[Path, Path]:
    """A 64 x 64 x 12 stack of the phantom brain (12 slices along ``slice_axis``) and its mask, as NIfTI."""
    from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine

    shape = [64, 64, 64]
    shape[slice_axis] = 12
    affine = stack_affine(slice_axis, np.eye(3), 2.0, 5.0, tuple(shape))
    image, mask = acquire_stack(*phantom_brain(7), affine, tuple(shape), slice_axis,
                                np.broadcast_to(np.eye(4), (12, 4, 4)))
    paths = directory / f"{name}.nii.gz", directory / f"{name}_mask.nii.gz"
    nib.save(nib.Nifti1Image((image * 10).astype(np.int16), affine), paths[0])
    nib.save(nib.Nifti1Image(mask.astype(np.uint8), affine), paths[1])
    return paths


@pytest.mark.slow
def test_end_to_end_against_a_real_server(tmp_path: Path) -> None:
    from tests.support.live_server import Server

    (ax, ax_mask), (cor, cor_mask) = phantom_stack(tmp_path, "ax", 2), phantom_stack(tmp_path, "cor", 1)
    server = Server(tmp_path / "data", tmp_path / "server.log")
    try:
        out = tmp_path / "messages.jsonl"
        result = runner.invoke(cli.app, ["stream", str(ax), str(cor), "--mask", str(ax_mask), "--mask", str(cor_mask),
                                         "--server", server.url, "--mc-samples", "10", "--no-bias-correction",
                                         "--order", "interleaved", "--json-out", str(out)])
    finally:
        server.stop(15)
        server.kill_group()
    assert result.exit_code in (0, exits.EXIT_NOTHING_USABLE), result.output + (tmp_path / "server.log").read_text()[-3000:]
    messages = [json.loads(line) for line in out.read_text().splitlines()]
    accepted = any(s["accepted"] for m in messages if m["type"] == "stack" for s in m["slices"])
    assert result.exit_code == (0 if accepted else exits.EXIT_NOTHING_USABLE)     # as predict: 12 when none is
    assert messages[0]["type"] == "ready" and messages[-1]["type"] == "summary"
    answers = [m["type"] for m in messages if m["type"] not in ("pose", "update")]
    assert answers == ["ready", "stack", "stack", "summary"]
    sent = [("ax", k) for k in send_order(12, "interleaved")] + [("cor", k) for k in send_order(12, "interleaved")]
    assert [(m["stack"], m["index"]) for m in messages if m["type"] == "pose"] == sent
    stacks = [m for m in messages if m["type"] == "stack"]
    assert [s["stack"] for s in stacks] == ["ax", "cor"]
    assert all(sorted(s["index"] for s in st["slices"]) == list(range(12)) for st in stacks)
    summary = messages[-1]
    assert summary["stacks"] == ["ax", "cor"] and summary["slices"] == 24
    assert "pose_latency_p95" in summary["timing_ms"] and 0.0 <= summary["coverage"]["brain_fraction"] <= 1.0
    text = " ".join(result.output.split())
    assert "stack ax:" in text and "stack cor:" in text and "session: 2 stack(s), 24 slices" in text


def test_a_slice_order_that_fits_no_stack_is_a_usage_error_before_anything_is_sent(stack_file: Path) -> None:
    for orders, needle in ((["0,1"], "each of the stack's"), (["zigzag"], "slice indices as acquired"),
                           (["sequential", "sequential"], "2 values for 1 stacks")):
        args = ["stream", str(stack_file), "--server", "http://127.0.0.1:9"]
        for o in orders:
            args += ["--slice-order", o]
        result = runner.invoke(cli.app, args, env={"COLUMNS": "200"})
        assert result.exit_code == 2 and needle in result.output, result.output


def test_a_library_caller_whose_session_ends_early_learns_what_was_answered_and_what_was_not(stack_file: Path) -> None:
    """A server that restarts after answering two slices: the error raised carries the session's
    messages so far (``result``) and, per stack, the slices sent but never answered (``unanswered``),
    to send again."""
    from client.errors import ConnectionFailed
    from client.stream import read_stack, stream_stacks

    received: list[int] = []

    def handler(ws: ServerConnection) -> None:
        ws.recv()
        ws.send(json.dumps({"type": "ready", "session_id": "s1", "model": {"name": "default"}, "mc_samples": 10}))
        for answered in range(3):
            msg = json.loads(ws.recv())
            ws.recv()
            received.append(msg["index"])
            if answered < 2:
                ws.send(json.dumps(pose(msg)))
        ws.close(1012, "service restart")

    with scripted_server(handler) as url, pytest.raises(ConnectionFailed, match="restarting") as e:
        stream_stacks([read_stack(stack_file)], url)
    poses = [m["index"] for m in e.value.result.of_type("pose")]
    assert poses == received[:2] and e.value.result.ready["session_id"] == "s1"
    assert received[2] in e.value.unanswered["ax"] and not set(poses) & set(e.value.unanswered["ax"])


def test_a_wss_server_of_a_sites_own_ca_is_trusted_where_its_bundle_is_given(
        stack_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The stream checks a ``wss://`` server's certificate as the HTTP calls do: refused with advice
    that keeps TLS where this client does not trust it; served with SVRNET_CA_BUNDLE naming the site's CA."""
    import ssl

    from client.errors import ConnectionFailed
    from client.stream import read_stack, stream_stacks
    from tests.support.certificates import self_signed

    cert, key = self_signed(tmp_path)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(cert, key)

    def handler(ws: ServerConnection) -> None:
        ws.recv()
        ws.send(json.dumps({"type": "ready", "session_id": "s1", "model": {"name": "default"}, "mc_samples": 10}))
        while True:
            msg = json.loads(ws.recv())
            if msg["type"] == "slice":
                ws.recv()
                ws.send(json.dumps(pose(msg)))
            elif msg["type"] == "end_stack":
                ws.send(json.dumps({"type": "stack", "stack": msg["stack"], "slices": []}))
            else:
                ws.send(json.dumps({"type": "summary", "stacks": []}))
                return

    monkeypatch.delenv("SVRNET_CA_BUNDLE", raising=False)
    with scripted_server(handler, ssl=context) as url:
        secure = url.replace("http://", "https://")
        with pytest.raises(ConnectionFailed, match="not one this client trusts: give your site's CA bundle"):
            stream_stacks([read_stack(stack_file)], secure)
        monkeypatch.setenv("SVRNET_CA_BUNDLE", str(cert))
        result = stream_stacks([read_stack(stack_file)], secure)
    assert result.summary == {"type": "summary", "stacks": []} and len(result.of_type("pose")) == 4
