"""A real ``svrnet-server`` on a socket: connections that never finish their headers are closed, a
stalled body gets its 408 and a closed connection, kept-alive and WebSocket connections are not cut."""

from __future__ import annotations

import json
import signal
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from websockets.sync.client import connect

from service.api.http_protocol import with_header_deadline
from tests.support.live_server import Server

LIMIT_S = 1.5


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    tmp = tmp_path_factory.mktemp("protocol")
    srv = Server(tmp / "data", tmp / "server.log", header_timeout_s=LIMIT_S, upload_idle_s=LIMIT_S,
                 upload_timeout_s=4)
    yield srv
    srv.stop(signal.SIGTERM)


def read_until_closed(sock: socket.socket, seconds: float, drip: bytes = b"") -> tuple[bytes, float | None]:
    """What the server sends until it closes the connection (and when), sending ``drip`` every 0.2 s."""
    sock.settimeout(0.2)
    t0, data = time.monotonic(), b""
    while time.monotonic() - t0 < seconds:
        try:
            if drip:
                sock.sendall(drip)
            chunk = sock.recv(65536)
        except socket.timeout:
            continue
        except OSError:                       # reset while dripping: closed
            return data, time.monotonic() - t0
        if not chunk:
            return data, time.monotonic() - t0
        data += chunk
    return data, None


def test_a_silent_connection_is_closed(server: Server) -> None:
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        data, closed_after = read_until_closed(sock, 10)
    assert data == b"" and closed_after is not None and closed_after < LIMIT_S + 2


def test_headers_trickled_line_by_line_are_cut_off(server: Server) -> None:
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        data, closed_after = read_until_closed(sock, 10, drip=b"X-Slow: 1\r\n")   # never the blank line
    assert data == b"" and closed_after is not None and closed_after < LIMIT_S + 2


def test_a_stalled_body_gets_408_and_the_connection_closes(server: Server) -> None:
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        sock.sendall(b"POST /v1/predict HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: multipart/form-data; boundary=xx\r\n"
                     b"Content-Length: 100000\r\n\r\n--xx\r\n")
        data, closed_after = read_until_closed(sock, 10)
    head, _, body = data.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 408") and b"connection: close" in head.lower(), head
    assert json.loads(body)["type"] == "/problems/request-timeout"
    assert closed_after is not None and closed_after < LIMIT_S + 2


def test_kept_alive_requests_each_get_their_own_deadline(server: Server) -> None:
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        sock.settimeout(5)
        for _ in range(4):                    # 4 x 0.6 deadlines on one connection: longer than one
            time.sleep(0.6 * LIMIT_S)
            sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            answer = b""
            while not answer.endswith(b"}"):  # the head and the body may come in two reads
                answer += sock.recv(65536)
            assert answer.startswith(b"HTTP/1.1 200") and b'"ok"' in answer, answer


def test_a_websocket_session_outlives_the_header_deadline(server: Server) -> None:
    with connect(server.url.replace("http", "ws") + "/v1/stream") as ws:
        time.sleep(LIMIT_S + 1)
        ws.send(json.dumps({"type": "start", "mc_samples": 2}))
        assert json.loads(ws.recv(timeout=30))["type"] == "ready"


def test_the_protocol_class_carries_its_deadline() -> None:
    assert with_header_deadline(2.5).header_timeout_s == 2.5
    assert Path(__file__).name.startswith("test_")
