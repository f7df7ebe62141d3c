"""``svrnet-mrd-send``: stack files sent to an ``svrnet-mrd`` server as a scanner sends them.

What a site sees before it connects a scanner: each stack file (any file ``/v1/predict`` takes, read
as it reads it, with its checks) becomes one MRD image series (``image_series_index`` = the file's
place on the command line), cut along its slice axis (the voxel axis of largest spacing) into 2D
magnitude images whose headers place every pixel where the file's affine does
(:func:`~service.mrd.images.image_from_slice`), sent in acquisition order (``--order``) over one
connection, the answers read as they come (:class:`MrdLink`). It prints one line per series
(images answered, the server's latency, accepted at once and finally, the median expected error,
slices worth acquiring again) and, with ``--out``, writes every answer as a JSON line: images as
``{"type": "image", "series", "slice", ...}`` with their pose (the ``SVRnet.*`` meta attributes,
:func:`~service.mrd.images.pose_from_meta`), TEXT messages as the server sent them.

When every series has as many slices, the XML header says so, and each series ends (its ``stack``
message) as soon as it has arrived; otherwise the series end at ``CLOSE``.

Exit codes (those of ``svrnet``): 0 once the server's summary arrived, 2 for bad options (a file that
does not exist among them), 3 when the server cannot be reached, does not answer in MRD, or ends the
session (or does not end it within ``--wait-s``) before its summary, 5 for a file that cannot be read
as a stack, 7 when the server's sessions are all taken (its error says when to retry).

Example:
    >>> send_order(5, "interleaved"), send_order(4, "3,2,1,0")
    ([0, 2, 4, 1, 3], [3, 2, 1, 0])
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import ismrmrd
import numpy as np
from ismrmrd.serialization import ConfigText

from service.consistency.slice_order import SliceOrder
from service.core.errors import ServiceError
from service.io.readers import read_upload
from service.io.volume import Volume
from service.mrd.images import image_from_slice, pose_from_meta
from service.preprocess.stack import slice_axis_of

DEFAULT_PORT = 9002
SEND_ORDERS = ("sequential", "interleaved", "interleaved-even-first", "interleaved-odd-first")
CONNECT_TIMEOUT_S = 10.0
EXIT_OK, EXIT_USAGE, EXIT_CONNECTION, EXIT_BAD_INPUT, EXIT_BUSY = 0, 2, 3, 5, 7
HEADER_XML = """<?xml version="1.0" encoding="utf-8"?>
<ismrmrdHeader xmlns="http://www.ismrm.org/ISMRMRD">
 <experimentalConditions><H1resonanceFrequency_Hz>63500000</H1resonanceFrequency_Hz></experimentalConditions>
 <encoding>
  <encodedSpace><matrixSize><x>1</x><y>1</y><z>1</z></matrixSize>
   <fieldOfView_mm><x>1</x><y>1</y><z>1</z></fieldOfView_mm></encodedSpace>
  <reconSpace><matrixSize><x>1</x><y>1</y><z>1</z></matrixSize>
   <fieldOfView_mm><x>1</x><y>1</y><z>1</z></fieldOfView_mm></reconSpace>
  <encodingLimits>{slice}</encodingLimits>
  <trajectory>cartesian</trajectory>
 </encoding>
</ismrmrdHeader>"""


def mrd_header(slices: int | None) -> ismrmrd.xsd.ismrmrdHeader:
    """An MRD XML header whose first encoding states ``slices`` slices a series (``None``: no limit;
    the server then ends each series at ``CLOSE``)."""
    limit = "" if slices is None else f"<slice><minimum>0</minimum><maximum>{slices - 1}</maximum><center>0</center></slice>"
    return ismrmrd.xsd.CreateFromDocument(HEADER_XML.replace("{slice}", limit))


def send_order(count: int, order: str = "sequential") -> list[int]:
    """The slice indices of a stack of ``count`` slices in the order a scanner acquires them: one of
    :data:`SEND_ORDERS` (``interleaved``: even indices first) or the indices themselves,
    comma-separated (:class:`ValueError`, saying why, otherwise)."""
    word = order.strip().lower()
    if word == "auto" or (word[:1].isalpha() and word not in SEND_ORDERS):
        raise ValueError(f"{order!r} is not an order to send in: one of {', '.join(SEND_ORDERS)}, "
                         "or the slice indices as acquired (0,2,4,1,3)")
    parsed = SliceOrder.parse("interleaved-even-first" if word == "interleaved" else order)
    times = next(iter(parsed.times(count).values()))
    return np.argsort(times, kind="stable").tolist()


def series_images(volume: Volume, series: int, order: str = "sequential") -> list[ismrmrd.Image]:
    """The MRD images of a stack, one per slice along its slice axis, in acquisition ``order``: image
    ``(x, y)`` is voxel ``(x, y)`` of the two in-plane axes in increasing order, its header placing it
    where ``volume.affine`` places that voxel (its axes made exactly orthogonal, as MRD's direction
    fields are); ``slice`` is the index along the slice axis, ``image_index`` the place in the order
    of sending."""
    axis = slice_axis_of(volume.spacing)
    first, second = [a for a in range(3) if a != axis]
    array = np.moveaxis(np.asarray(volume.array, np.float32), (first, second, axis), (0, 1, 2))
    base = np.asarray(volume.affine, np.float64)[:, [first, second, axis, 3]]
    spacing = np.linalg.norm(base[:3, :3], axis=0)
    u, _, vt = np.linalg.svd(base[:3, :3] / spacing)      # a scanner's directions are orthonormal: the nearest such
    base[:3, :3] = (u @ vt) * spacing                      # (a file's sform may be sheared by up to 0.06 deg)
    images = []
    for sent, k in enumerate(send_order(array.shape[2], order)):
        placed = base.copy()
        placed[:3, 3] = base[:3, 3] + k * base[:3, 2]
        images.append(image_from_slice(array[:, :, k], placed, series=series, slice_index=k, image_index=sent))
    return images


def answer_record(message: Any) -> dict[str, Any]:
    """What the server sent, as one JSON object: an image's series, slice and pose, or a TEXT message."""
    if isinstance(message, ismrmrd.Image):
        return {"type": "image", "series": int(message.image_series_index), "slice": int(message.slice),
                **pose_from_meta(message.meta)}
    if isinstance(message, str):
        try:
            record = json.loads(message)
        except ValueError:
            record = None
        return record if isinstance(record, dict) and "type" in record else {"type": "text", "text": message}
    return {"type": type(message).__name__}


class MrdLink:
    """One connection to an MRD server: messages out, and every message back collected by a thread of
    its own (so that neither side waits for the other to read) until the server's ``CLOSE``."""

    def __init__(self, host: str, port: int, on_message: Callable[[Any], None] | None = None,
                 keep: bool = True) -> None:
        self.sock = socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S)
        self.sock.settimeout(None)                 # the server's own limits end a session that stalls
        self.writer = self.sock.makefile("wb")
        self.outgoing = ismrmrd.ProtocolSerializer(self.writer)
        self.received: list[Any] = []
        """Every message received (with ``keep``; a caller whose ``on_message`` takes them keeps none)."""
        self.keep = keep
        self.closed_by_server = False
        self.timed_out = False
        """Whether :meth:`wait` gave up before the server ended the connection."""
        self.unreadable: Exception | None = None
        """What made the server's bytes unreadable as MRD messages (not an MRD server), if anything."""
        self.on_message = on_message
        self.failure: Exception | None = None
        """What ``on_message`` raised first (re-raised by :meth:`wait`; the messages are still all read)."""
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        incoming = ismrmrd.ProtocolDeserializer(self.sock.makefile("rb"))
        try:
            for message in incoming.deserialize():
                if self.keep:
                    self.received.append(message)
                if self.on_message is not None and self.failure is None:
                    try:
                        self.on_message(message)
                    except Exception as exc:  # noqa: BLE001 - kept for wait(); the reading goes on
                        self.failure = exc
            self.closed_by_server = True
        except (EOFError, OSError):
            pass
        except Exception as exc:  # noqa: BLE001 - ismrmrd's parsers raise many kinds on bytes that are not MRD
            self.unreadable = exc

    def send(self, *messages: Any) -> None:
        for message in messages:
            self.outgoing.serialize(message)
        self.writer.flush()

    def close(self, wait_s: float = 600.0) -> list[Any]:
        """Send ``CLOSE``; wait for the server's; everything received."""
        try:
            self.outgoing.close()
        except OSError:
            pass
        return self.wait(wait_s)

    def wait(self, wait_s: float = 600.0) -> list[Any]:
        """Wait (at most ``wait_s``) for the server to end the connection, then end it here too (the
        reader stops); everything received. Re-raises what ``on_message`` raised."""
        self._reader.join(timeout=wait_s)
        self.timed_out = self._reader.is_alive()
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._reader.join(timeout=5.0)
        for closing in (self.writer, self.sock):
            try:
                closing.close()
            except OSError:
                pass
        if self.failure is not None:
            raise self.failure
        return self.received


@dataclass
class SeriesTally:
    """What came back for one series: its images' immediate answers, and its slices' poses as the
    ``stack`` message gave them and later ``update`` messages moved them (a later series can move and
    accept an ended one's slices)."""

    name: str
    sent: int
    answered: int = 0
    accepted_at_once: int = 0
    latency_ms: list[float] = field(default_factory=list)
    final: dict[tuple[str, int], dict[str, Any]] = field(default_factory=dict)
    reacquire: dict[str, int] = field(default_factory=dict)

    def take(self, record: dict[str, Any]) -> None:
        """Count an answer of this series (an ``image`` record, its ``stack`` or ``update`` message)."""
        kind = record["type"]
        if kind == "image":
            self.answered += 1
            self.accepted_at_once += bool(record.get("accepted"))
            self.latency_ms.append(float(record.get("latency_ms") or 0.0))
            return
        stack = str(record.get("stack"))
        if kind == "stack" or (kind == "update" and any(name == stack for name, _ in self.final)):
            self.final.update({(stack, int(s["index"])): s for s in record.get("slices", [])})
            if "reacquire" in record:
                self.reacquire[stack] = len(record["reacquire"])

    def line(self) -> str:
        latency = (f" (server latency p50 / p95 {np.percentile(self.latency_ms, 50):.0f} / "
                   f"{np.percentile(self.latency_ms, 95):.0f} ms)" if self.latency_ms else "")
        text = f"{self.name}: {self.answered} of {self.sent} answered{latency}, {self.accepted_at_once} accepted at once"
        if not self.final:
            return text + "; no final poses"
        final = list(self.final.values())
        expected = [s["expected_error_mm"] for s in final if s.get("expected_error_mm") is not None]
        median = f"{np.median(expected):.1f} mm" if expected else "-"
        accepted = sum(bool(s.get("accepted")) for s in final)
        return (text + f"; final: {accepted} of {len(final)} accepted, median expected error {median}, "
                f"{sum(self.reacquire.values())} worth acquiring again")


@dataclass
class Session:
    """What came back from one connection: each series' tally, every TEXT message, and why it ended
    early (``problem``; None once the summary arrived)."""

    tallies: list[SeriesTally]
    texts: list[dict[str, Any]]
    problem: str | None = None

    @property
    def refused_as_busy(self) -> bool:
        """The server refused the session: its sessions were all taken (an error with ``retry_after_s``
        that names no image)."""
        return any(t.get("type") == "error" and t.get("status") == 503 and "retry_after_s" in t
                   and "image_series_index" not in t for t in self.texts)


class LinkError(Exception):
    """The server could not be reached."""


def send_series(series: Sequence[Sequence[ismrmrd.Image]], names: Sequence[str], host: str, port: int,
                config: dict[str, Any] | None = None, pace_s: float = 0.0, out: IO[str] | None = None,
                wait_s: float = 600.0) -> Session:
    """Send image ``series`` (:func:`series_images`; ``names`` for the tallies) over one connection,
    ``pace_s`` seconds between images, and wait at most ``wait_s`` for the server's end of it. Every
    answer goes to ``out`` as a JSON line as it arrives.

    Raises:
        LinkError: the server cannot be reached.
    """
    tallies = [SeriesTally(name, len(images)) for name, images in zip(names, series)]
    texts: list[dict[str, Any]] = []

    def on_message(message: Any) -> None:
        record = answer_record(message)
        if out is not None:
            out.write(json.dumps(record) + "\n")
        if record["type"] != "image":
            texts.append(record)
        series_index = record.get("series", str(record.get("stack", "")).split(".")[0])
        if str(series_index).isdigit() and int(series_index) < len(tallies):
            tallies[int(series_index)].take(record)

    counts = {len(images) for images in series}
    header = mrd_header(counts.pop() if len(counts) == 1 else None)
    try:
        link = MrdLink(host, port, on_message=on_message, keep=False)
    except OSError as e:
        raise LinkError(f"{host}:{port}: {e.strerror or e}") from None
    try:
        link.send(ismrmrd.ConfigFile("svrnet"), ConfigText(json.dumps(config or {})), header)
        for images in series:
            for image in images:
                link.send(image)
                if pace_s > 0:
                    time.sleep(pace_s)
    except OSError:                      # the server ended the session (busy, a broken stream): what it said is read
        link.wait(wait_s)
    else:
        link.close(wait_s)
    session = Session(tallies, texts)
    if not any(t.get("type") == "summary" for t in texts):
        session.problem = ("the server's answers are not MRD messages (is it an svrnet-mrd server?)" if link.unreadable
                           else f"no end of the session from the server within {wait_s:g} s" if link.timed_out
                           else "the server ended the session before its summary")
    return session


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="svrnet-mrd-send", description="Send stack files to an svrnet-mrd server "
                                 "as MRD images, as a scanner sends them, and show what comes back.")
    ap.add_argument("stacks", nargs="+", type=Path, help="stack files (NIfTI, NRRD, MHA, DICOM, a ZIP of one DICOM "
                    "series); one MRD series each")
    ap.add_argument("--host", default="127.0.0.1", help="the server's address (default 127.0.0.1)")
    ap.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"its port (default {DEFAULT_PORT})")
    ap.add_argument("--order", default="sequential", help="acquisition order: sequential, interleaved (even "
                    "indices first), interleaved-even-first, interleaved-odd-first, or the slice indices as "
                    "acquired (0,2,4,1,3)")
    ap.add_argument("--config", default="{}", help='session options as JSON, e.g. \'{"mc_samples": 50}\'')
    ap.add_argument("--pace-s", type=float, default=0.0, help="seconds between images (a scanner's pace)")
    ap.add_argument("--wait-s", type=float, default=600.0, help="how long to wait for the server's last answers")
    ap.add_argument("--out", type=Path, help="write every answer as a JSON line to this file")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        config = json.loads(args.config)
        if not isinstance(config, dict):
            raise ValueError("not a JSON object")
    except ValueError as e:
        return _fail(f"--config: {e}", EXIT_USAGE)
    try:
        send_order(len(args.order.split(",")), args.order)   # indices given: as many as there are, per file below
    except ValueError as e:
        return _fail(f"--order: {e}", EXIT_USAGE)
    series = []
    for i, path in enumerate(args.stacks):
        if not path.is_file():                                # a mistyped name is no corrupt file
            return _fail(f"{path}: no such file", EXIT_USAGE)
        try:
            volume = read_upload(path, path.name)             # as /v1/predict reads a file, with its checks
        except ServiceError as e:
            return _fail(e.detail, EXIT_BAD_INPUT)
        try:
            series.append(series_images(volume, i, args.order))
        except ValueError as e:
            return _fail(f"--order: {path.name}: {e}", EXIT_USAGE)
    try:
        out = open(args.out, "w", encoding="utf-8") if args.out else None
    except OSError as e:
        return _fail(f"--out: {args.out}: {e.strerror or e}", EXIT_USAGE)
    names = [f"series {i} ({path.name})" for i, path in enumerate(args.stacks)]
    try:
        session = send_series(series, names, args.host, args.port, config, args.pace_s, out, args.wait_s)
    except LinkError as e:
        return _fail(str(e), EXIT_CONNECTION)
    finally:
        if out is not None:
            out.close()
    for tally in session.tallies:
        print(tally.line())
    for error in (t for t in session.texts if t.get("type") == "error"):
        retry = f" (retry after {error['retry_after_s']} s)" if "retry_after_s" in error else ""
        print(f"error {error.get('status')}: {error.get('detail')}{retry}", file=sys.stderr)
    if session.problem is not None:
        return _fail(session.problem, EXIT_BUSY if session.refused_as_busy else EXIT_CONNECTION)
    return EXIT_OK


def _fail(message: str, code: int) -> int:
    print(f"svrnet-mrd-send: {message}", file=sys.stderr)
    return code


def run() -> None:
    """Console entry point."""
    sys.exit(main())
