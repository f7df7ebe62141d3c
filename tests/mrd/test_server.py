"""``svrnet-mrd`` end to end: a client sends simulated stacks as MRD images over TCP and gets every
image back, in order, with the pose of the simulated truth as meta attributes; each series' final
poses; the summary; and errors that name the message at fault while the session goes on."""

from __future__ import annotations

import json
import select
import socket
import struct
import threading
import time

import ismrmrd
import numpy as np
import pytest
from ismrmrd.serialization import ConfigText

from service.inference.registry import ModelRegistry
from service.mrd.images import pixel_count, pose_from_meta
from service.mrd.send import MrdLink, mrd_header
from service.mrd.server import MrdServer, ServerLimits, session_factory
from service.streaming.options import StreamLimits
from tests.mrd.conftest import Case
from tests.support.streams import true_sent

CONFIG = ConfigText(json.dumps({"mc_samples": 10, "bias_correction": False}))
INTERLEAVED = list(range(0, 20, 2)) + list(range(1, 20, 2))


def texts(received: list) -> list[dict]:
    return [json.loads(m) for m in received if isinstance(m, str)]


def test_every_image_comes_back_in_order_with_its_true_pose(case: Case, serve) -> None:  # noqa: ANN001
    server = serve()
    client = MrdLink("127.0.0.1", server.port)
    client.send(ismrmrd.ConfigFile("svrnet"), CONFIG, mrd_header(slices=20))
    sent = [case.images[series][k] for series in (0, 1) for k in INTERLEAVED]
    client.send(*sent)
    received = client.close()
    assert client.closed_by_server

    images = [m for m in received if isinstance(m, ismrmrd.Image)]
    assert [(i.image_series_index, i.slice) for i in images] == [(i.image_series_index, i.slice) for i in sent]
    for back, image in zip(images, sent):
        np.testing.assert_array_equal(back.data, image.data)
        assert bytes(back.getHead())[:-4] == bytes(image.getHead())[:-4]        # all but attribute_string_len
        pose = pose_from_meta(back.meta)
        assert pose["accepted"] in (True, False) and pose["latency_ms"] >= 0
        truth = true_sent(case.truths[back.image_series_index], back.slice)
        np.testing.assert_allclose(pose["atlas_from_voxel"], truth, atol=1e-3)

    kinds = [("image", m.image_series_index) if isinstance(m, ismrmrd.Image) else json.loads(m)["type"]
             for m in received if not (isinstance(m, str) and json.loads(m)["type"] == "update")]
    assert kinds == [("image", 0)] * 20 + ["stack"] + [("image", 1)] * 20 + ["stack", "summary"]
    messages = texts(received)
    stacks = [m for m in messages if m["type"] == "stack"]
    assert [s["stack"] for s in stacks] == ["0", "1"]
    for series, stack in enumerate(stacks):
        final = np.array([s["atlas_from_voxel"] for s in stack["slices"]])
        truth = np.stack([true_sent(case.truths[series], k) for k in range(20)])
        assert np.linalg.norm(final[:, :3, 3] - truth[:, :3, 3], axis=1).max() < 0.5
    summary = messages[-1]
    assert summary["stacks"] == ["0", "1"] and summary["slices"] == 40
    timing = summary["timing_ms"]                                      # as Stream v1's summary
    assert timing["session"] > 0 and timing["pose_latency_p95"] >= timing["pose_latency_p50"] > 0


class TightServer(MrdServer):
    """The server with socket buffers of a few kilobytes per connection: a client's unread answers
    fill them after a message or two, as tens of megabytes of answers fill a real socket's."""

    def server_bind(self) -> None:
        for option in (socket.SO_SNDBUF, socket.SO_RCVBUF):    # the accepted sockets inherit them
            self.socket.setsockopt(socket.SOL_SOCKET, option, 4096)
        super().server_bind()


def test_a_client_that_reads_only_after_sending_everything_gets_every_answer(case: Case) -> None:
    factory = session_factory(ModelRegistry({"default": case.oracle}), case.localiser, StreamLimits())  # type: ignore[dict-item]
    server = TightServer(("127.0.0.1", 0), factory, StreamLimits(), ServerLimits(idle_s=30.0))   # not the limit under test
    threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
    try:
        sock = socket.socket()
        for option in (socket.SO_SNDBUF, socket.SO_RCVBUF):      # as small as the server's
            sock.setsockopt(socket.SOL_SOCKET, option, 4096)
        sock.settimeout(60)
        sock.connect(("127.0.0.1", server.port))
        writer = sock.makefile("wb")
        outgoing = ismrmrd.ProtocolSerializer(writer)
        sent = [case.images[series][k] for series in (0, 1) for k in range(20)]
        for message in (ismrmrd.ConfigFile("svrnet"), CONFIG, mrd_header(slices=20), *sent):
            outgoing.serialize(message)
        outgoing.close()                                # CLOSE, and only now the client reads
        writer.flush()
        received = list(ismrmrd.ProtocolDeserializer(sock.makefile("rb")).deserialize())
        sock.close()
    finally:
        server.shutdown()
        server.server_close()
    images = [m for m in received if isinstance(m, ismrmrd.Image)]
    assert [(i.image_series_index, i.slice) for i in images] == [(i.image_series_index, i.slice) for i in sent]
    assert [m["type"] for m in texts(received) if m["type"] != "update"] == ["stack", "stack", "summary"]


def test_a_client_that_never_reads_loses_its_session_and_frees_the_slot(case: Case) -> None:
    factory = session_factory(ModelRegistry({"default": case.oracle}), case.localiser, StreamLimits())  # type: ignore[dict-item]
    server = TightServer(("127.0.0.1", 0), factory, StreamLimits(), ServerLimits(max_sessions=1, idle_s=1.0))
    threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
    mute = socket.socket()
    for option in (socket.SO_SNDBUF, socket.SO_RCVBUF):
        mute.setsockopt(socket.SOL_SOCKET, option, 4096)
    mute.settimeout(60)
    try:
        mute.connect(("127.0.0.1", server.port))
        writer = mute.makefile("wb")
        outgoing = ismrmrd.ProtocolSerializer(writer)
        for message in (CONFIG, *case.images[0][:10]):              # then silence, reading nothing
            outgoing.serialize(message)
        writer.flush()
        deadline, answered = time.monotonic() + 60, None
        while answered is None:                                     # the slot frees once the idle limit ends it
            assert time.monotonic() < deadline, "the slot stayed taken"
            other = MrdLink("127.0.0.1", server.port)
            try:
                other.send(CONFIG, case.images[1][0])
            except OSError:
                pass                                                # refused: the server closed first
            received = other.close()
            answered = next((m for m in received if isinstance(m, ismrmrd.Image)), None)
            if answered is None:
                assert texts(received)[0]["status"] == 503
                time.sleep(0.5)
    finally:
        mute.close()
        server.shutdown()
        server.server_close()
    assert answered.image_series_index == 1


def image_like(image: ismrmrd.Image, data: np.ndarray, **fields: object) -> ismrmrd.Image:
    """An image with ``image``'s header but other data (``[channels, z, y, x]``) and ``fields``."""
    out = ismrmrd.Image(head=image.getHead(), data=data)
    for name, value in fields.items():
        setattr(out, name, value)
    return out


def test_unusable_messages_get_an_error_and_the_session_goes_on(case: Case, serve) -> None:  # noqa: ANN001
    server = serve()
    client = MrdLink("127.0.0.1", server.port)
    first = case.images[0][0]
    plane = first.data
    client.send(ConfigText('{"mc_samples": 0}'), CONFIG,
                image_like(first, plane, image_type=ismrmrd.IMTYPE_PHASE),
                image_like(first, np.repeat(plane, 3, axis=1)),                    # 3D: z = 3
                image_like(first, np.repeat(plane, 2, axis=0)),                    # two channels
                image_like(first, np.repeat(plane, 300, axis=1)),                  # a volume over the pixel limit
                image_like(first, np.repeat(plane, 300, axis=0)),                  # uncombined coils, over it too
                ismrmrd.Acquisition.from_array(np.zeros((2, 16), np.complex64)),
                ismrmrd.Acquisition.from_array(np.zeros((2, 16), np.complex64)))
    client.send(*[case.images[0][k] for k in INTERLEAVED])                         # no header: the stack ends at CLOSE
    received = client.close()
    assert client.closed_by_server

    errors = [m for m in texts(received) if m["type"] == "error"]
    details = [e["detail"] for e in errors]
    assert len(errors) == 7, details
    assert pixel_count(image_like(first, np.repeat(plane, 300, axis=1))) > StreamLimits().max_pixels
    for words, error in zip(["config.mc_samples", "image_type: phase", "matrix_size: a 3D image", "channels: 2",
                             "matrix_size: a 3D image", "channels: 300", "acquisition"], errors):
        assert words in error["detail"] and error["status"] in (400, 422) and error["problem_type"].startswith("/problems/")
    assert errors[1]["image_series_index"] == 0 and errors[1]["slice"] == 0
    images = [m for m in received if isinstance(m, ismrmrd.Image)]
    assert [i.slice for i in images] == INTERLEAVED
    assert all("SVRnet.AtlasFromVoxel" in i.meta for i in images)
    kinds = [m["type"] for m in texts(received) if m["type"] != "update"]
    assert kinds[-2:] == ["stack", "summary"]


def test_a_slice_beyond_the_headers_count_is_refused_and_the_series_ends_with_the_others(case: Case, serve) -> None:  # noqa: ANN001
    """A series numbered from 1 would wait for its slice 0 and end without it: its last slice is named
    on arrival, in the header's terms."""
    server = serve()
    client = MrdLink("127.0.0.1", server.port)
    last = case.images[0][19]
    client.send(CONFIG, mrd_header(slices=20), image_like(last, last.data, slice=20))
    client.send(*[case.images[0][k] for k in INTERLEAVED])
    received = client.close()
    errors = [m for m in texts(received) if m["type"] == "error"]
    assert len(errors) == 1 and errors[0]["slice"] == 20
    assert errors[0]["detail"].startswith("image slice: 20 is beyond the header's 20 slices")
    assert [m["stack"] for m in texts(received) if m["type"] == "stack"] == ["0"]


def test_a_series_without_a_slice_ends_at_close_naming_it(case: Case, serve) -> None:  # noqa: ANN001
    """A dropped image costs its series that slice alone: the series ends at ``CLOSE`` with it blank,
    ``not_received`` and listed to acquire again."""
    server = serve()
    client = MrdLink("127.0.0.1", server.port)
    client.send(CONFIG, mrd_header(slices=20), *[case.images[0][k] for k in range(20) if k != 6])
    received = client.close()
    messages = texts(received)
    assert not [m for m in messages if m["type"] == "error"]
    (stack,) = [m for m in messages if m["type"] == "stack"]
    assert len(stack["slices"]) == 20 and [k for k, s in enumerate(stack["slices"]) if s["reason"] == "not_received"] == [6]
    assert {"index": 6, "reason": "not_received"} in stack["reacquire"]
    summary = messages[-1]
    assert summary["type"] == "summary" and summary["unfinished"] == {}
    assert {"index": 6, "reason": "not_received"} in summary["reacquire"]["0"]


def test_a_series_with_most_of_its_slices_missing_is_named_in_mrd_terms(case: Case, serve) -> None:  # noqa: ANN001
    server = serve()
    client = MrdLink("127.0.0.1", server.port)
    client.send(CONFIG, *[case.images[0][k] for k in (2, 3, 19)])        # no header: the series ends at CLOSE
    received = client.close()
    (error,) = [m for m in texts(received) if m["type"] == "error"]
    assert error["detail"].startswith("series: stack '0' lacks the slices [0, 1, 4, 5") and error["image_series_index"] == 0
    summary = texts(received)[-1]                  # not a clean session: the series is named with what it lacks
    assert summary["type"] == "summary" and summary["reacquire"] == {}
    assert summary["unfinished"] == {"0": {"missing": [k for k in range(19) if k not in (2, 3)]}}


def test_slices_sent_again_after_their_series_ended_are_told_why_they_get_no_stack(case: Case, serve) -> None:  # noqa: ANN001
    """A complete series, then two of its slices again (as its ``stack`` message's ``reacquire`` asks):
    they form the series' second pass, which cannot end as a stack of its own; the error says so in
    the series' terms, not by the slices the scanner was never asked for, and the summary names it."""
    server = serve()
    client = MrdLink("127.0.0.1", server.port)
    client.send(CONFIG, mrd_header(slices=20), *case.images[0], case.images[0][5], case.images[0][9])
    received = client.close()
    messages = texts(received)
    assert [m["stack"] for m in messages if m["type"] == "stack"] == ["0"]
    assert len([m for m in received if isinstance(m, ismrmrd.Image)]) == 22          # each image answered at once
    (error,) = [m for m in messages if m["type"] == "error"]
    assert error["image_series_index"] == 0 and error["detail"].startswith(
        "series 0: the slices [5, 9] came after the series had ended; they make a pass of their own (stack '0.2')")
    assert messages[-1]["unfinished"] == {"0.2": {"missing": [0, 1, 2, 3, 4, 6, 7, 8]}}


def test_an_image_over_the_pixel_limit_is_refused_before_its_data(case: Case, serve) -> None:  # noqa: ANN001
    server = serve(StreamLimits(max_pixels=32 * 32))
    client = MrdLink("127.0.0.1", server.port)
    try:
        client.send(case.images[0][0])
    except OSError:
        pass                                            # the server may have closed while the data went out
    received = client.wait()
    assert client.closed_by_server
    (error,) = texts(received)
    assert error["type"] == "error" and error["status"] == 413 and "limit of 1024 pixels" in error["detail"]


def test_sessions_over_the_limit_are_told_to_retry(case: Case, serve) -> None:  # noqa: ANN001
    server = serve(limits=ServerLimits(max_sessions=1))
    holder = MrdLink("127.0.0.1", server.port)
    holder.send(CONFIG, case.images[0][0])
    while not holder.received:                          # the first session holds the slot once it answers
        holder._reader.join(timeout=0.05)
    other = MrdLink("127.0.0.1", server.port)
    (error,) = texts(other.wait())
    assert other.closed_by_server
    assert error["status"] == 503 and error["retry_after_s"] >= 1
    assert isinstance(holder.close()[0], ismrmrd.Image)


def test_a_refused_client_that_leaves_first_is_no_server_error(case: Case, serve, monkeypatch) -> None:  # noqa: ANN001
    """Its answer meets a reset connection: logged as the client's leaving, not a traceback of the
    server's, and the session holding the slot goes on."""
    import service.mrd.server as mrd_server

    server = serve(limits=ServerLimits(max_sessions=1))
    faults: list[object] = []
    monkeypatch.setattr(server, "handle_error", lambda request, address: faults.append(address))
    holder = MrdLink("127.0.0.1", server.port)
    holder.send(CONFIG, case.images[0][0])
    while not holder.received:
        holder._reader.join(timeout=0.05)

    def reset(*args: object, **kwargs: object) -> None:
        raise ConnectionResetError(104, "Connection reset by peer")

    monkeypatch.setattr(mrd_server, "refuse", reset)
    with socket.create_connection(("127.0.0.1", server.port)) as gone:
        gone.settimeout(5)
        assert gone.recv(1) == b""                                          # the server closed it
    assert isinstance(holder.close()[0], ismrmrd.Image) and faults == []     # the session held goes on


@pytest.mark.parametrize("silent_s", [0.2])
def test_a_silent_connection_is_closed_with_an_error(serve, silent_s: float) -> None:  # noqa: ANN001
    server = serve(limits=ServerLimits(idle_s=silent_s))
    client = MrdLink("127.0.0.1", server.port)
    (error,) = texts(client.wait())
    assert client.closed_by_server and "no message for too long" in error["detail"] and error["status"] == 408



def test_a_client_that_trickles_a_message_is_closed_like_a_silent_one(serve) -> None:  # noqa: ANN001
    # An image's header a byte at a time, each byte well within the idle limit: the message as a
    # whole is not, and the session slot is not held for ever.
    server = serve(limits=ServerLimits(idle_s=1.0))
    sock = socket.create_connection(("127.0.0.1", server.port), timeout=10)
    t0, answered = time.monotonic(), None
    try:
        for byte in int(ismrmrd.serialization.ISMRMRDMessageID.IMAGE).to_bytes(2, "little") + bytes(300):
            sock.sendall(bytes([byte]))
            if select.select([sock], [], [], 0.1)[0]:   # the server answered: when
                answered = time.monotonic() - t0
                break
            if time.monotonic() - t0 > 5:
                break
    except OSError:
        pass
    sock.settimeout(5)
    received = b""
    while chunk := sock.recv(1 << 16):
        received += chunk
    sock.close()
    assert b"no message for too long" in received
    assert answered is not None and answered < 3.0, f"the server kept a trickling connection open ({answered})"


def test_a_broken_stream_is_drained_for_the_linger_in_all_not_per_byte(serve, monkeypatch) -> None:  # noqa: ANN001
    """After a broken stream the server drains what the client still sends for LINGER_S in all: a client
    that sends a byte now and then within each read's wait held the thread (and the socket) for
    256 of those waits."""
    from service.mrd import server as server_module

    monkeypatch.setattr(server_module, "LINGER_S", 0.5)
    spans: list[float] = []
    real = server_module.MrdHandler.linger

    def timed(self) -> None:  # noqa: ANN001
        t0 = time.monotonic()
        real(self)
        spans.append(time.monotonic() - t0)

    monkeypatch.setattr(server_module.MrdHandler, "linger", timed)
    server = serve()
    sock = socket.create_connection(("127.0.0.1", server.port), timeout=10)
    sock.sendall(b"\xff\xff")                                  # an unknown message: the stream is broken
    t0 = time.monotonic()
    try:
        while time.monotonic() - t0 < 2.5 and not spans:
            sock.sendall(b"x")
            time.sleep(0.2)
    except OSError:
        pass
    sock.close()
    deadline = time.monotonic() + 5
    while not spans and time.monotonic() < deadline:
        time.sleep(0.05)
    assert spans and spans[0] < 1.5, spans


def test_the_mrd_server_listens_on_an_ipv6_address(case: Case) -> None:
    """``--host ::1`` (or ``SVRNET_HOST=::``, which the HTTP server takes) binds: socketserver's family
    is IPv4's, and svrnet-mrd ended in a traceback."""
    factory = session_factory(ModelRegistry({"default": case.oracle}), case.localiser, StreamLimits())  # type: ignore[dict-item]
    try:
        server = MrdServer(("::1", 0), factory, StreamLimits())
    except OSError as exc:                   # a host without IPv6
        pytest.skip(f"no IPv6 loopback here: {exc}")
    try:
        threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
        socket.create_connection(("::1", server.port), timeout=5).close()
    finally:
        server.shutdown()
        server.server_close()


def test_the_mrd_servers_limits_on_its_command_line_are_numbers_over_zero(capsys) -> None:  # noqa: ANN001
    """0, a negative number or NaN is a usage error: 0 turned into the default in disguise, a negative
    session count was a traceback, a negative idle time a server that dropped every connection."""
    from service.mrd import server as server_module

    for option, value in (("--max-sessions", "0"), ("--max-sessions", "-2"), ("--idle-s", "-1"), ("--idle-s", "nan")):
        with pytest.raises(SystemExit) as stopped:
            server_module.parser().parse_args([option, value])
        assert stopped.value.code == 2 and "a number over 0 is required" in capsys.readouterr().err, (option, value)
    args = server_module.parser().parse_args(["--max-sessions", "3", "--idle-s", "2.5"])
    assert (args.max_sessions, args.idle_s) == (3, 2.5)


def test_the_mrd_servers_port_is_a_port_number(capsys) -> None:  # noqa: ANN001
    """A port over 65535 resolved (wrapped round) and bound in the address check, then the server's own
    bind raised a traceback; a negative one blamed the host."""
    from service.mrd import server as server_module

    for value in ("70000", "-1", "http"):
        with pytest.raises(SystemExit) as stopped:
            server_module.parser().parse_args(["--port", value])
        assert stopped.value.code == 2 and "a port is a whole number from 0 to 65535" in capsys.readouterr().err
    assert server_module.parser().parse_args(["--port", "0"]).port == 0


def test_an_mrd_server_without_a_default_localiser_stops_in_one_line(monkeypatch, capsys) -> None:  # noqa: ANN001
    """Its images carry no masks: a localiser named otherwise is no default (a traceback before)."""
    from service.core.settings import Settings
    from service.mrd import server as server_module
    from service.preprocess.localise import Localisers

    monkeypatch.setattr(ModelRegistry, "from_directory", classmethod(lambda cls, *a, **k: cls({"default": object()})))
    monkeypatch.setattr(Localisers, "from_directory", classmethod(lambda cls, *a, **k: cls({"fetal-v2": object()})))
    with pytest.raises(SystemExit) as stopped:
        server_module.build_server(Settings(), "127.0.0.1", 0, ServerLimits())
    assert stopped.value.code == 2
    assert "no 'default' localiser" in (err := capsys.readouterr().err) and "(found: fetal-v2)" in err


@pytest.mark.parametrize(("limit", "slices"), [("<maximum>19</maximum>", 20), ("", None), ("<maximum></maximum>", None),
                                               ("<maximum>-3</maximum>", None), ("<maximum>0</maximum>", None)])
def test_a_header_gives_the_slices_of_a_series_only_when_it_says_so(limit: str, slices: int | None) -> None:
    # An absent, empty or negative maximum once ended a stack after every image.
    from types import SimpleNamespace

    from service.mrd.connection import MrdConnection
    from service.mrd.send import HEADER_XML

    connection = SimpleNamespace(slices_per_series=-1)
    header = ismrmrd.xsd.CreateFromDocument(HEADER_XML.replace(
        "{slice}", f"<slice><minimum>0</minimum>{limit}<center>0</center></slice>"))   # the parser reads "" as 0
    MrdConnection.on_header(connection, header)
    assert connection.slices_per_series == slices


def test_images_after_a_refused_config_are_refused_not_posed_with_defaults(case: Case, serve) -> None:  # noqa: ANN001
    """A config the server refuses leaves the session without options: its images get errors that
    name the refused config, not poses made with the defaults the client did not ask for."""
    server = serve()
    client = MrdLink("127.0.0.1", server.port)
    client.send(ConfigText('{"mc_samples": 0, "bias_correction": false}'), *case.images[0][:3])
    received = client.close()
    errors = [m["detail"] for m in texts(received) if m["type"] == "error"]
    assert "config.mc_samples" in errors[0], errors
    assert len(errors) >= 4 and all("config was refused" in e and "config.mc_samples" in e for e in errors[1:4]), errors
    assert not [m for m in received if isinstance(m, ismrmrd.Image)]
    summary = texts(received)[-1]              # the session ends as every session does: its (empty) summary
    assert summary["type"] == "summary" and summary["stacks"] == [] and summary["slices"] == 0


def test_a_text_message_that_cannot_be_parsed_is_a_bad_request_not_an_unusable_image(serve) -> None:  # noqa: ANN001
    server = serve()
    client = MrdLink("127.0.0.1", server.port)
    text = b"\xff\xfe not utf-8"
    client.writer.write(int(ismrmrd.serialization.ISMRMRDMessageID.TEXT).to_bytes(2, "little")
                        + len(text).to_bytes(4, "little") + text)
    client.writer.flush()
    received = texts(client.close())
    (error,) = [m for m in received if m["type"] == "error"]
    assert error["status"] == 400 and "text: the message could not be parsed" in error["detail"], error
    assert received[-1]["type"] == "summary"


def test_an_image_errors_name_the_mrd_header_fields(case: Case, serve) -> None:  # noqa: ANN001
    """A geometry no acquisition has (30 mm pixels) is refused in the image header's own terms."""
    server = serve()
    client = MrdLink("127.0.0.1", server.port)
    first = case.images[0][0]
    nx = first.matrix_size[0]
    huge = image_like(first, first.data)
    huge.field_of_view = (30.0 * nx, 30.0 * first.matrix_size[1], float(first.field_of_view[2]))
    client.send(CONFIG, huge)
    (error,) = [m for m in texts(client.close()) if m["type"] == "error"]
    assert error["status"] == 400 and error["slice"] == first.slice, error
    assert error["detail"].startswith("image header (position, read_dir, phase_dir, slice_dir, field_of_view): ")
    assert "scanner_from_voxel" not in error["detail"] and "20 mm" in error["detail"], error


def test_a_connection_that_fails_unexpectedly_is_logged_by_type_and_place_only(serve, monkeypatch, capfd,  # noqa: ANN001
                                                                               caplog) -> None:  # noqa: ANN001
    """socketserver's own handler prints the traceback, whose message may quote what the client sent,
    and the client's address; the server logs the failure's type and place, and frees the slot."""
    import logging

    import service.mrd.server as mrd_server

    def fail(self: object) -> None:
        raise RuntimeError("DOE^JANE 1970-01-01")

    server = serve(limits=ServerLimits(max_sessions=1))
    monkeypatch.setattr(mrd_server.MrdConnection, "run", fail)
    with caplog.at_level(logging.ERROR, logger="service.mrd.server"):
        for _ in range(2):                                                  # the one slot is free again
            with socket.create_connection(("127.0.0.1", server.port)) as gone:
                gone.sendall(b"\x01")                                      # a first byte: the session starts
                gone.settimeout(5)
                assert gone.recv(1) == b""
        deadline = time.monotonic() + 5
        while len([r for r in caplog.records if r.getMessage() == "mrd connection failed"]) < 2:
            assert time.monotonic() < deadline
            time.sleep(0.02)
    failed = [r for r in caplog.records if r.getMessage() == "mrd connection failed"]
    assert {r.error_type for r in failed} == {"RuntimeError"}
    out, err = capfd.readouterr()
    assert "DOE^JANE" not in out + err + caplog.text and "Traceback" not in err


def test_raw_data_is_read_past_without_being_built(case: Case, serve, monkeypatch) -> None:  # noqa: ANN001
    """Acquisitions, waveforms and NDArrays are skipped by their heads' sizes (``ismrmrd`` would
    allocate what a head announces before reading it): each kind named once, the images answered."""
    def built(*args: object) -> None:
        raise AssertionError("a raw-data message was built")

    monkeypatch.setattr(ismrmrd.Acquisition, "deserialize_from", staticmethod(built))
    monkeypatch.setattr(ismrmrd.Waveform, "deserialize_from", staticmethod(built))
    server = serve()
    client = MrdLink("127.0.0.1", server.port)
    wave = ismrmrd.Waveform.from_array(np.arange(12, dtype=np.uint32).reshape(3, 4))
    client.send(CONFIG, mrd_header(slices=20), ismrmrd.Acquisition.from_array(np.ones((2, 16), np.complex64)), wave,
                np.ones((3, 5), np.float32), wave, ismrmrd.Acquisition.from_array(np.ones((1, 8), np.complex64)))
    client.send(*[case.images[0][k] for k in INTERLEAVED])
    received = client.close()
    errors = [m for m in texts(received) if m["type"] == "error"]
    assert [e["detail"].split(":")[0] for e in errors] == ["acquisition", "waveform", "ndarray"]
    assert [i.slice for i in received if isinstance(i, ismrmrd.Image)] == INTERLEAVED
    assert [m["stack"] for m in texts(received) if m["type"] == "stack"] == ["0"]


def test_an_acquisition_announcing_more_data_than_the_limit_is_refused_before_it_is_read(serve) -> None:  # noqa: ANN001
    head = ismrmrd.AcquisitionHeader(number_of_samples=65535, active_channels=65535, trajectory_dimensions=3)
    error = only_error(serve(), struct.pack("<H", int(ismrmrd.serialization.ISMRMRDMessageID.ACQUISITION)) + bytes(head))
    assert error["status"] == 413 and error["detail"].startswith("acquisition: its head announces 34359476220 bytes")


def only_error(server: MrdServer, raw: bytes) -> dict:
    """The one message a server answers ``raw`` bytes with, then closes (it may close while they go out)."""
    client = MrdLink("127.0.0.1", server.port)
    try:
        client.writer.write(raw)
        client.writer.flush()
    except OSError:
        pass
    received = client.wait()
    assert client.closed_by_server
    (error,) = texts(received)
    return error


def test_an_image_with_meta_attributes_over_the_limit_is_refused_before_they_are_read(case: Case, serve) -> None:  # noqa: ANN001
    """Parsed into a tree, a text of empty elements took over twenty times its size in memory, up to
    the whole read limit (16 MiB): the attributes' length is checked after the header."""
    from service.mrd.protocol import MAX_META_BYTES

    announced = MAX_META_BYTES + 1
    error = only_error(serve(), struct.pack("<H", int(ismrmrd.serialization.ISMRMRDMessageID.IMAGE))
                       + bytes(case.images[0][0].getHead()) + struct.pack("<Q", announced) + b"<a/>" * 1000)
    assert error["status"] == 413 and error["detail"].startswith(f"image: meta attributes of {announced} bytes")


def test_an_image_with_meta_attributes_under_the_limit_is_posed_and_keeps_them(case: Case, serve) -> None:  # noqa: ANN001
    server = serve()
    client = MrdLink("127.0.0.1", server.port)
    first = case.images[0][0]
    tagged = ismrmrd.Image(head=first.getHead(), data=first.data)
    tagged.meta["ImageComments"] = "x" * 20000
    client.send(CONFIG, tagged)
    received = client.close()
    (image,) = [m for m in received if isinstance(m, ismrmrd.Image)]
    assert image.meta["ImageComments"] == "x" * 20000 and "SVRnet.AtlasFromVoxel" in image.meta


def test_a_client_sending_only_ignored_messages_loses_its_slot_at_the_idle_limit(case: Case, serve) -> None:  # noqa: ANN001
    """Each message started the idle deadline again: an NDArray now and then held the one session slot
    for ever, and other scanners got 503. Only messages the server takes count."""
    server = serve(limits=ServerLimits(max_sessions=1, idle_s=1.0))
    client = MrdLink("127.0.0.1", server.port)
    started = time.monotonic()
    try:
        while time.monotonic() - started < 3.0 and not client.closed_by_server:
            client.send(np.zeros(4, np.float32))
            time.sleep(0.3)
    except OSError:
        pass                                            # the server closed while the array went out
    received = client.wait(5.0)
    assert client.closed_by_server and time.monotonic() - started < 3.0
    errors = [m for m in texts(received) if m["type"] == "error"]
    assert errors[0]["detail"].startswith("ndarray: svrnet-mrd takes reconstructed images")
    assert errors[-1]["status"] == 408 and "no message the server takes for 1 s" in errors[-1]["detail"]
    second = MrdLink("127.0.0.1", server.port)                  # the slot is free again
    second.send(CONFIG, mrd_header(slices=20), *[case.images[0][k] for k in INTERLEAVED])
    assert [m["stack"] for m in texts(second.close()) if m["type"] == "stack"] == ["0"]


def test_the_servers_own_work_on_a_stack_is_not_the_clients_idle_time(case: Case, serve, monkeypatch) -> None:  # noqa: ANN001
    """A stack's end that takes longer than the idle limit (a large stack, a busy CPU) does not close
    a client whose next images wait in the socket."""
    from service.streaming.session import StreamSession

    ending = StreamSession.end_stack

    def slow(self, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        time.sleep(1.5)
        return ending(self, *args, **kwargs)

    monkeypatch.setattr(StreamSession, "end_stack", slow)
    server = serve(limits=ServerLimits(idle_s=1.0))
    client = MrdLink("127.0.0.1", server.port)
    client.send(CONFIG, mrd_header(slices=20), *[case.images[s][k] for s in (0, 1) for k in INTERLEAVED])
    received = client.close()
    assert [m["stack"] for m in texts(received) if m["type"] == "stack"] == ["0", "1"]
    assert not [m for m in texts(received) if m["type"] == "error"]


def test_a_silent_connection_holds_no_session_slot_and_a_probe_logs_at_debug(serve, caplog,  # noqa: ANN001
                                                                               monkeypatch) -> None:  # noqa: ANN001
    """A slot was taken at ``accept``: a peer that connects and sends nothing held it for the idle limit
    (32 such kept every scanner out, answered 503), and compose's health check (an empty connection
    every 30 s) logged a line at INFO each time. Now the slot waits for the first bytes, which a
    silent peer does not send within ``FIRST_BYTES_S``; a session is still logged at INFO."""
    import logging

    import service.mrd.server as mrd_server

    monkeypatch.setattr(mrd_server, "FIRST_BYTES_S", 0.5)
    server = serve(limits=ServerLimits(max_sessions=1))
    with caplog.at_level(logging.DEBUG, logger="service.mrd"):
        socket.create_connection(("127.0.0.1", server.port), 3).close()          # the health check
        silent = socket.create_connection(("127.0.0.1", server.port), 3)         # holds no slot
        with socket.create_connection(("127.0.0.1", server.port), 3) as client:
            client.sendall(struct.pack("<H", 4))                                 # CLOSE: the one slot is free
            client.settimeout(5)
            answered = b""
            while chunk := client.recv(4096):
                answered += chunk
        silent.settimeout(5)
        told = b""
        while chunk := silent.recv(4096):                                        # told, then closed
            told += chunk
        silent.close()
    assert b"MRD sessions are open" not in answered
    assert b'"status": 408' in told and b"before the first" in told
    levels = {(r.getMessage().split(" within")[0], r.levelno) for r in caplog.records
              if r.getMessage().startswith("mrd connection")}
    assert levels == {("mrd connection closed before its first message", logging.DEBUG),
                      ("mrd connection sent nothing", logging.INFO), ("mrd connection ended: closed", logging.INFO)}


def test_a_stopping_server_tells_each_open_session_to_send_again(case: Case, serve) -> None:  # noqa: ANN001
    """Half a series sent, then the server stops (SIGTERM's path): the scanner gets a 503 ``error``
    with ``retry_after_s`` and the server's ``CLOSE``, not a connection that just ends."""
    server = serve()
    client = MrdLink("127.0.0.1", server.port)
    client.send(CONFIG, mrd_header(slices=20), *[case.images[0][k] for k in INTERLEAVED[:10]])
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and (not server.live or len(client.received) < 10):   # answered so far
        time.sleep(0.05)
    assert server.tell_stopping(grace_s=5.0) == 1
    received = client.wait(30)
    assert client.closed_by_server and not client.timed_out
    last = texts(received)[-1]
    assert (last["type"], last["status"]) == ("error", 503) and last["retry_after_s"] > 0, last
    assert "stopping" in last["detail"]
    assert len([m for m in received if isinstance(m, ismrmrd.Image)]) == 10


def test_the_mrd_port_stays_on_the_loopback_unless_its_own_option_opens_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """MRD carries no key: ``SVRNET_HOST=0.0.0.0``, set to open the HTTP API (with its keys) to the
    network, leaves svrnet-mrd on 127.0.0.1; only ``--host`` opens it."""
    from service.mrd import server as server_module

    monkeypatch.setenv("SVRNET_HOST", "0.0.0.0")
    asked: list[str] = []

    def listening_on(settings: object, host: str, port: int, limits: object) -> None:
        asked.append(host)
        raise SystemExit(0)                          # where it would listen is all this test asks

    monkeypatch.setattr(server_module, "build_server", listening_on)
    for argv, host in (([], "127.0.0.1"), (["--host", "0.0.0.0"], "0.0.0.0")):
        with pytest.raises(SystemExit):
            server_module.main(["--port", "0", *argv])
        assert asked[-1] == host
