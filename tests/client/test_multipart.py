"""The client's streamed ``multipart/form-data`` body, parsed back by the standard library and by the
parser the server uses (python-multipart)."""

from __future__ import annotations

import email
import email.policy
from pathlib import Path

import pytest

from client.multipart import CHUNK, MultipartBody, form_value, order_fields, quote_param


def parse(body: MultipartBody, data: bytes) -> list[tuple[str, str | None, bytes]]:
    """[(field name, filename or None, payload)] of a body, via the stdlib's MIME parser."""
    head = f"Content-Type: {body.content_type}\r\nMIME-Version: 1.0\r\n\r\n".encode()
    msg = email.message_from_bytes(head + data, policy=email.policy.HTTP)
    assert msg.is_multipart()
    return [(p.get_param("name", header="content-disposition"), p.get_filename(), p.get_payload(decode=True))
            for p in msg.iter_parts()]


@pytest.fixture
def big_file(tmp_path: Path) -> Path:
    """A file spanning several chunks, with a partial last chunk."""
    path = tmp_path / "stack.nii.gz"
    path.write_bytes(bytes(range(256)) * (2 * CHUNK // 256) + b"tail")
    return path


def test_the_body_is_its_declared_length_and_round_trips(big_file: Path) -> None:
    body = MultipartBody([("mc_samples", form_value(50)), ("bias_correction", form_value(False))],
                         [("stacks", big_file.name, big_file, "application/gzip"),
                          ("masks", "m.nii", b"\x00\x01\r\n--x", "application/octet-stream")])
    data = b"".join(body.chunks())
    assert len(data) == body.total
    parts = parse(body, data)
    assert [(n, f) for n, f, _ in parts] == [("mc_samples", None), ("bias_correction", None),
                                              ("stacks", "stack.nii.gz"), ("masks", "m.nii")]
    assert parts[0][2] == b"50" and parts[1][2] == b"false"
    assert parts[2][2] == big_file.read_bytes()
    assert parts[3][2] == b"\x00\x01\r\n--x"


def test_a_retry_resends_the_same_bytes_and_progress_counts_to_the_total(big_file: Path) -> None:
    body = MultipartBody([("x", "1")], [("stacks", "a.nii.gz", big_file, "application/gzip")])
    seen: list[tuple[int, int]] = []
    first = b"".join(body.chunks(lambda sent, total: seen.append((sent, total))))
    assert b"".join(body.chunks()) == first
    sent = [s for s, _ in seen]
    assert seen[0] == (0, body.total) and seen[-1] == (body.total, body.total)
    assert sent == sorted(sent) and max(b - a for a, b in zip(sent, sent[1:])) <= CHUNK


def test_names_with_quotes_and_line_breaks_cannot_break_the_framing() -> None:
    name = 'evil"; filename="x\r\nContent-Type: text/html'
    body = MultipartBody([], [("stacks", name, b"data", "application/gzip")])
    parts = parse(body, b"".join(body.chunks()))
    assert len(parts) == 1 and parts[0][2] == b"data"
    assert "\r" not in parts[0][1] and "\n" not in parts[0][1]
    assert quote_param('a"b\\c') == 'a%22b\\\\c'


def test_the_server_side_parser_reads_the_body(big_file: Path) -> None:
    multipart = pytest.importorskip("python_multipart", reason="python-multipart (a server dependency)")
    body = MultipartBody([("slice_order", "interleaved")], [("stacks", "s.nii.gz", big_file, "application/gzip")])
    got: dict[str, bytes] = {}
    fields: list[tuple[bytes, bytes]] = []

    def on_file(f) -> None:  # noqa: ANN001 - python-multipart's File
        f.file_object.seek(0)
        got[f.file_name.decode()] = f.file_object.read()

    parser = multipart.create_form_parser({"Content-Type": body.content_type.encode()},
                                          lambda f: fields.append((f.field_name, f.value)), on_file)
    for chunk in body.chunks():
        parser.write(chunk)
    parser.finalize()
    assert fields == [(b"slice_order", b"interleaved")]
    assert got == {"s.nii.gz": big_file.read_bytes()}


def test_slice_orders_repeat_the_field_once_per_value() -> None:
    assert order_fields(None) == []
    assert order_fields("interleaved") == [("slice_order", "interleaved")]
    assert order_fields(["sequential", "0,2,1"]) == [("slice_order", "sequential"), ("slice_order", "0,2,1")]
    assert form_value(True) == "true" and form_value(0.8) == "0.8"
