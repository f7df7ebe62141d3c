"""The MRD answers' outbox: a client that reads only after it has sent gets every answer, in order;
what waits unsent is bounded; a client that reads nothing, or is gone, ends the connection."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator

import pytest

from service.mrd.outbox import Outbox

SMALL_BUFFER = 4096


@pytest.fixture
def pair() -> Iterator[tuple[socket.socket, socket.socket]]:
    """A connected pair whose kernel buffers hold a few kilobytes, so that unread answers block a
    plain writer after a few messages."""
    server_end, client_end = socket.socketpair()
    for sock in (server_end, client_end):
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SMALL_BUFFER)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SMALL_BUFFER)
    yield server_end, client_end
    server_end.close()
    client_end.close()


def read_all(sock: socket.socket, n: int) -> bytes:
    out = bytearray()
    while len(out) < n:
        chunk = sock.recv(1 << 16)
        if not chunk:
            break
        out += chunk
    return bytes(out)


def test_answers_far_beyond_the_socket_buffers_are_queued_and_arrive_in_order(pair: tuple[socket.socket, socket.socket]) -> None:
    server_end, client_end = pair
    box = Outbox(server_end, idle_s=10.0)
    messages = [bytes([k]) * 50_000 for k in range(40)]                # 2 MB against buffers of kilobytes
    for m in messages:              # nothing read yet: a write that waited for the reader would time out
        box.write(m[:10])
        box.write(memoryview(m)[10:])
        box.flush()
    got = read_all(client_end, sum(map(len, messages)))
    assert box.drain(5.0) and got == b"".join(messages)


def test_past_the_unread_limit_the_answering_side_waits_then_gives_up(pair: tuple[socket.socket, socket.socket]) -> None:
    server_end, client_end = pair
    box = Outbox(server_end, idle_s=0.5, max_unread_bytes=200_000)
    with pytest.raises(TimeoutError, match="read none of its answers"):
        for _ in range(100):
            box.write(b"x" * 50_000)
            box.flush()
    assert not box.drain(0.1)


def test_a_client_that_reads_once_it_has_sent_gets_everything_even_past_the_limit(pair: tuple[socket.socket, socket.socket]) -> None:
    server_end, client_end = pair
    box = Outbox(server_end, idle_s=10.0, max_unread_bytes=100_000)
    total = 40 * 50_000
    reader = threading.Timer(0.3, lambda: got.append(read_all(client_end, total)))
    got: list[bytes] = []
    reader.start()                                                      # reads later: flush waits for it
    for k in range(40):
        box.write(bytes([k]) * 50_000)
        box.flush()
    assert box.drain(10.0)
    reader.join()
    assert got[0] == b"".join(bytes([k]) * 50_000 for k in range(40))


def test_a_client_gone_ends_the_answers(pair: tuple[socket.socket, socket.socket]) -> None:
    server_end, client_end = pair
    box = Outbox(server_end, idle_s=5.0)
    client_end.close()
    with pytest.raises(ConnectionError):
        for _ in range(50):
            box.write(b"y" * 50_000)
            box.flush()
            time.sleep(0.01)
    assert not box.drain(1.0)
