"""Stream v1 from the scanner side: stack files sent slice by slice over ``/v1/stream`` (``docs/stream.md``).

A stack file is cut along its slice axis (the voxel axis of largest spacing, ties to the last, as
``/v1/predict`` does) into the 2D slices a scanner would send (:mod:`client.scanner_stack`, whose
names this module re-exports); :func:`stream_stacks` sends them in one session over
:func:`websockets.sync.client.connect`, a few slices ahead of their poses, and hands every message
the server sends to a callback.

Example:
    >>> from client.stream import read_stack, stream_stacks
    >>> stack = read_stack("ax.nii.gz", mask_path="ax_mask.nii.gz")                 # doctest: +SKIP
    >>> result = stream_stacks([stack], "http://127.0.0.1:8000", mc_samples=20)      # doctest: +SKIP
    >>> len(result.of_type("pose")), result.summary["coverage"]["brain_fraction"]    # doctest: +SKIP
    (22, 0.41)
"""

from __future__ import annotations

import json
import os
import ssl
import time
from collections import deque
from collections.abc import Callable, Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
from websockets.exceptions import ConnectionClosed, InvalidStatus, InvalidURI, WebSocketException
from websockets.sync.client import ClientConnection, connect

from client.transport import USER_AGENT, clean_api_key, server_address, trusted
from client._client import DEFAULT_SERVER
from client.errors import (ArgumentError, Busy, ConnectionFailed, ServerError, SVRnetError, Unauthorized,
                           UnusableInput, error_class_for_status)
from client.scanner_stack import SENT_DTYPES, ScannerSlice, ScannerStack, read_stack, scanner_slices, slice_axis_of

__all__ = ["ScannerSlice", "ScannerStack", "Sent", "StreamResult", "ORDERS", "slice_axis_of", "scanner_slices",
           "read_stack", "send_order", "stream_url", "stream_stacks"]

ORDERS = ("sequential", "interleaved", "interleaved-even-first", "interleaved-odd-first")
"""The named acquisition orders (``/v1/predict``'s ``slice_order`` words); slice indices as acquired
(``0,2,4,1,3``) are taken too."""
MAX_IN_FLIGHT = 4
"""Slices sent ahead of their poses at most, so that a slow server is never buried."""
SESSION_FULL = "/problems/session-full"
"""The problem type of a slice refused because the session holds all the slices or memory it may:
the client sends no more and names what is left (:attr:`StreamResult.unsent`)."""
OPEN_TIMEOUT_S = 10.0
MAX_MESSAGE_BYTES = 64 << 20
"""Largest message taken from the server (a ``stack`` message of a long stack is a few MB)."""

MessageCallback = Callable[[dict[str, Any], "Sent | None"], None]


@dataclass(frozen=True)
class Sent:
    """A message the client sent and the server answers: its ``type``, and ``stack`` and ``index`` where it has them."""

    type: str
    stack: str | None = None
    index: int | None = None


@dataclass
class StreamResult:
    """Every message of a session, in the order received (``messages``), its ``ready`` and ``summary``,
    and the slices it could not take (``unsent``)."""

    ready: dict[str, Any] = field(default_factory=dict)
    messages: list[dict[str, Any]] = field(default_factory=list)
    summary: dict[str, Any] | None = None
    unsent: dict[str, list[int]] = field(default_factory=dict)
    """Per stack, the slices the session could not take (the server's session held all the slices or
    memory it may), in index order; send them in another session."""

    def of_type(self, kind: str) -> list[dict[str, Any]]:
        """The messages of one type (``pose``, ``update``, ``stack``, ``error`` ...), in order."""
        return [m for m in self.messages if m.get("type") == kind]


def send_order(count: int, order: str = "sequential") -> list[int]:
    """The slice indices of a stack of ``count`` slices in the order they are sent (acquired): one of
    :data:`ORDERS` (``interleaved``: even indices first) or the indices themselves, comma-separated.

    Example:
        >>> send_order(5, "sequential"), send_order(5, "interleaved"), send_order(5, "interleaved-odd-first")
        ([0, 1, 2, 3, 4], [0, 2, 4, 1, 3], [1, 3, 0, 2, 4])
        >>> send_order(3, "2,0,1")
        [2, 0, 1]
    """
    evens, odds = list(range(0, count, 2)), list(range(1, count, 2))
    order = order.strip()
    named = {"sequential": list(range(count)), "interleaved": evens + odds, "interleaved-even-first": evens + odds,
             "interleaved-odd-first": odds + evens}
    if order in named:
        return named[order]
    try:
        indices = [int(k) for k in order.split(",")]
    except ValueError:
        raise ArgumentError(f"order: {order!r} is none of {', '.join(ORDERS)}, nor slice indices as acquired "
                            "(0,2,4,1,3)") from None
    if sorted(indices) != list(range(count)):
        raise ArgumentError(f"order: {order!r} does not list each of the stack's {count} slices (0..{count - 1}) once")
    return indices


def stream_url(server: str) -> str:
    """The WebSocket address of ``/v1/stream`` on a server given by its HTTP(S) address.

    Example:
        >>> stream_url("http://127.0.0.1:8000"), stream_url("https://svr.example/api/")
        ('ws://127.0.0.1:8000/v1/stream', 'wss://svr.example/api/v1/stream')
    """
    schemes = {"http": "ws", "https": "wss", "ws": "ws", "wss": "wss"}
    scheme, _, rest = server_address(server.strip(), tuple(schemes)).strip().partition("://")
    return f"{schemes[scheme.lower()]}://{rest.rstrip('/')}/v1/stream"


def _server_error(message: dict[str, Any], key_sent: bool | None = None) -> SVRnetError:
    """The client error of an ``error`` message (a ``Busy`` with ``retry_after_s`` where it says; an
    ``Unauthorized`` saying whether the session sent a key)."""
    status = message.get("status") if isinstance(message.get("status"), int) else 400
    detail = str(message.get("detail") or message.get("title") or f"error {status}")
    kwargs = {"status": status, "title": message.get("title"), "type": message.get("problem_type"), "body": message}
    cls = error_class_for_status(status, message.get("problem_type"))
    if cls is Busy:
        return Busy(detail, retry_after_s=message.get("retry_after_s"), **kwargs)
    if issubclass(cls, Unauthorized):
        return cls(detail, key_sent=key_sent, **kwargs)
    return cls(detail, **kwargs)


class _Session:
    """One connection: sends what the client has, reads what the server answers (one thread)."""

    def __init__(self, ws: ClientConnection, on_message: MessageCallback | None, record: IO[str] | None,
                 answer_timeout_s: float, key_sent: bool = False) -> None:
        self.ws, self.on_message, self.record, self.answer_timeout_s = ws, on_message, record, answer_timeout_s
        self.key_sent = key_sent
        self.unanswered: deque[Sent] = deque()
        self.result = StreamResult()
        self.last_error: dict[str, Any] | None = None
        self.full = False                       # the server refused a slice because the session holds all it may
        self.posed: set[str] = set()            # stacks with at least one slice taken

    def send(self, header: dict[str, Any], *frames: bytes) -> None:
        """A text message and its binary frames; it is then owed one answer."""
        self.unanswered.append(Sent(header["type"], header.get("stack"), header.get("index")))
        try:
            self.ws.send(json.dumps(header))
            for frame in frames:
                self.ws.send(frame)
        except ConnectionClosed:
            while True:                   # what the server said before it closed, then why it closed
                self.receive(None)

    def wait_to_send(self, not_before: float, max_in_flight: int) -> None:
        """Handle messages until fewer than ``max_in_flight`` slices await their pose and the clock
        (``time.monotonic``) has passed ``not_before``; then those that have come already."""
        while sum(1 for s in self.unanswered if s.type == "slice") >= max_in_flight:
            self.receive(None)
        while time.monotonic() < not_before:
            self.receive(not_before - time.monotonic())
        while self.receive(0):
            pass

    def receive(self, timeout: float | None) -> bool:
        """Handle the next message; False when none came within ``timeout`` seconds (``None``: the
        answer timeout, then :class:`ConnectionFailed`)."""
        try:
            data = self.ws.recv(timeout=self.answer_timeout_s if timeout is None else max(timeout, 0.0))
        except TimeoutError:
            if timeout is None:
                raise ConnectionFailed(f"no answer from the server in {self.answer_timeout_s:g} s") from None
            return False
        except ConnectionClosed as e:
            raise self.closed_error(e) from None
        self.handle(data)
        return True

    def handle(self, data: str | bytes) -> None:
        """Record a message, match it to the message it answers (every message of the client gets one
        answer, in order; an ``update`` answers none) and hand both to the callback."""
        try:
            message = json.loads(data) if isinstance(data, str) else None
        except ValueError:
            raise ServerError(f"the server sent a text frame that is no JSON: {data[:80]!r}") from None
        if not isinstance(message, dict):
            return
        if self.record is not None:
            self.record.write(json.dumps(message) + "\n")
            self.record.flush()
        self.result.messages.append(message)
        kind = message.get("type")
        answered = self.unanswered.popleft() if kind != "update" and self.unanswered else None
        if kind == "ready":
            self.result.ready = message
        elif kind == "summary":
            self.result.summary = message
        elif kind == "pose" and answered is not None:
            self.posed.add(str(answered.stack))
        elif kind == "error":
            self.last_error = message
            if answered is not None and answered.type == "slice" and message.get("problem_type") == SESSION_FULL:
                self.full = True
                self.result.unsent.setdefault(str(answered.stack), []).append(int(answered.index))
            if (answered is not None and answered.type in ("start", "end")) or message.get("status") == 401:
                raise _server_error(message, self.key_sent)
        if self.on_message is not None:
            self.on_message(message, answered)

    def closed_error(self, e: ConnectionClosed) -> SVRnetError:
        """Why the server closed the session early: a refusal (1008, 1013) as its last ``error`` says,
        a restart (1012) as what to do, else the close code and reason (or, for an idle session, 1001,
        its ``error``'s detail)."""
        code, reason = (e.rcvd.code, e.rcvd.reason) if e.rcvd is not None else (1006, str(e))
        said = self.last_error or {}
        if code in (1008, 1013) and said:
            return _server_error(said, self.key_sent)
        if code == 1013:
            return Busy("the server is busy (close code 1013)", status=503)
        if code == 1012:
            return ConnectionFailed("the server is restarting (close code 1012, service restart): the session is "
                                    "lost; stream the stacks again once it answers")
        why = said.get("detail") if code == 1001 and said else reason
        return ConnectionFailed(f"the server closed the stream (close code {code}{': ' + why if why else ''})")


def stream_stacks(stacks: Sequence[ScannerStack], server: str | None = None, *, api_key: str | None = None,
                  mc_samples: int | None = None, variance_threshold: float | None = None,
                  max_expected_error_mm: float | None = None, bias_correction: bool | None = None,
                  masks_hold_csf: bool | None = None, model: str | None = None, pace_s: float = 0.0, order: str | Sequence[str] = "sequential",
                  on_message: MessageCallback | None = None, json_out: str | Path | None = None,
                  answer_timeout_s: float = 300.0, max_in_flight: int = MAX_IN_FLIGHT) -> StreamResult:
    """Stream stacks in one session: ``start``, every slice of each stack then its ``end_stack``, ``end``.

    Slices go out every ``pace_s`` seconds (0: as fast as the answers come), at most
    ``max_in_flight`` of them ahead of their poses. An ``error`` answering a slice or an ``end_stack``
    is handed to ``on_message`` and the session goes on; one answering ``start`` or ``end``, or a 401, ends it.

    Args:
        stacks: the stacks, in the order they are sent (see :func:`read_stack`).
        server: the server's address (``http(s)://`` or ``ws(s)://``; default ``$SVRNET_SERVER``, else
            the local server), as :class:`~client.SVRnetClient` takes it.
        api_key: sent as ``Authorization: Bearer`` (default ``$SVRNET_API_KEY``).
        mc_samples: MC-dropout passes per slice (server default 100).
        variance_threshold: as for ``/v1/predict`` (default: the model's).
        max_expected_error_mm: as for ``/v1/predict`` (default: the model's).
        bias_correction: N4 bias-field correction (server default true).
        masks_hold_csf: the masks are the skull's inside, brain and CSF (server default false).
        model: the model's name (server default ``default``).
        pace_s: seconds between two slices.
        order: the order each stack's slices go out in (:func:`send_order`): one for every stack, or
            one per stack.
        on_message: called with every message received and the message of the client it answers
            (``None`` for an ``update``).
        json_out: where every message received is written, one JSON object a line (a file there is
            left as it was when no connection opens).
        answer_timeout_s: the longest wait for an answer before :class:`ConnectionFailed`.
        max_in_flight: slices sent ahead of their poses at most.

    Returns:
        Every message received; its ``summary`` is that of the session.

    Raises:
        ConnectionFailed: no connection, no answer, or the server closed the session early.
        Unauthorized: a missing or wrong API key. Busy: the server's sessions are all taken (1013).
        UnusableInput: stacks or slices over the server's ``ready.limits`` (before any is sent). Where
            the session fills up as it goes (its memory), the rest of the slices are not sent, the
            stacks begun are ended, and ``unsent`` names what is left.
        SVRnetError: the server refused ``start`` or ``end`` (its error's class).

        Every error raised once the connection is open carries ``result`` (the session's messages so
        far, a :class:`StreamResult`) and ``unanswered`` (per stack, the indices of the slices sent
        and never answered): what to keep, and what to send again.
    """
    options = {"model": model, "mc_samples": mc_samples, "variance_threshold": variance_threshold,
               "max_expected_error_mm": max_expected_error_mm, "bias_correction": bias_correction,
               "masks_hold_csf": masks_hold_csf}
    per_stack = [order] if isinstance(order, str) else list(order)
    if len(per_stack) == 1:
        per_stack *= len(stacks)
    if len(per_stack) != len(stacks):
        raise ArgumentError(f"order: {len(per_stack)} values for {len(stacks)} stacks; give one for every stack or one "
                            "per stack")
    orders = []
    for stack, o in zip(stacks, per_stack):
        try:
            orders.append(send_order(len(stack.slices), o))
        except ArgumentError as e:
            raise ArgumentError(f"{stack.name}: {e}") from None
    key = clean_api_key(api_key if api_key is not None else os.environ.get("SVRNET_API_KEY"))
    server = server or os.environ.get("SVRNET_SERVER") or DEFAULT_SERVER
    session = None
    try:
        with _connect(stream_url(server), key, answer_timeout_s) as ws, \
                (open(json_out, "w", encoding="utf-8") if json_out is not None else nullcontext()) as record:
            session = _Session(ws, on_message, record, answer_timeout_s, key_sent=bool(key))    # the file kept if none
            return _stream(session, stacks, orders, options, pace_s, max_in_flight)
    except SVRnetError as exc:
        if session is not None:                 # what the session answered, and what it did not
            exc.result = session.result
            exc.unanswered = {}
            for sent in session.unanswered:
                if sent.type == "slice":
                    exc.unanswered.setdefault(str(sent.stack), []).append(int(sent.index))
        raise


def _stream(session: "_Session", stacks: Sequence[ScannerStack], orders: list[list[int]], options: dict[str, Any],
            pace_s: float, max_in_flight: int) -> StreamResult:
    """:func:`stream_stacks`'s session once connected: ``start``, the stacks' slices and ends, ``end``."""
    session.send({"type": "start", **{k: v for k, v in options.items() if v is not None}})
    while not session.result.ready:
        session.receive(None)
    _check_limits(stacks, session.result.ready.get("limits") or {}, pace_s)
    next_send = time.monotonic()
    for stack, indices in zip(stacks, orders):
        for position, k in enumerate(indices):
            session.wait_to_send(next_send, max_in_flight)
            if session.full:                # nothing more is taken: the rest waits for another session
                session.result.unsent.setdefault(stack.name, []).append(k)
                continue
            header, frames = _slice_message(stack.name, stack.slices[k], position)
            session.send(header, *frames)
            next_send = time.monotonic() + pace_s
        if session.full:                    # the answers of the slices sent, to know which stacks began
            session.wait_to_send(0.0, 1)
        if not session.full or stack.name in session.posed:      # a stack none of whose slices was taken
            session.send({"type": "end_stack", "stack": stack.name})    # cannot end
    session.result.unsent = {name: sorted(ks) for name, ks in session.result.unsent.items()}
    session.send({"type": "end"})
    while session.result.summary is None:
        session.receive(None)
    return session.result


def _connect(url: str, api_key: str | None, answer_timeout_s: float) -> ClientConnection:
    """The open WebSocket (its pings wait for a pong as long as for an answer; a ``wss://`` server's
    certificate checked as the HTTP calls check it, :func:`~client.transport.trusted`); a refusal as a
    client error."""
    check = trusted(None) if url.lower().startswith("wss://") else True
    tls = {"ssl": check} if isinstance(check, ssl.SSLContext) else {}      # else websockets' own default
    try:
        return connect(url, additional_headers={"Authorization": f"Bearer {api_key}"} if api_key else None,
                       open_timeout=OPEN_TIMEOUT_S, ping_timeout=answer_timeout_s, max_size=MAX_MESSAGE_BYTES,
                       user_agent_header=USER_AGENT, **tls)
    except InvalidStatus as e:
        status = e.response.status_code
        if status in (403, 404):              # the key is checked after the handshake, not by it
            raise ConnectionFailed(f"{url}: the server refused the WebSocket ({status}): no stream at that address "
                                   "(give --server the server's root, e.g. http://host:8000, not a path below it)",
                                   status=status) from None
        raise error_class_for_status(status)(f"{url}: the server refused the WebSocket ({status})",
                                             status=status) from None
    except ssl.SSLCertVerificationError as e:
        raise ConnectionFailed(f"cannot open {url}: {type(e).__name__}: {e} (its certificate is not one this client "
                               "trusts: give your site's CA bundle with SVRNET_CA_BUNDLE)") from None
    except (OSError, TimeoutError, InvalidURI, WebSocketException) as e:
        raise ConnectionFailed(f"cannot open {url}: {type(e).__name__}: {e}") from None


def _check_limits(stacks: Sequence[ScannerStack], limits: dict[str, Any], pace_s: float = 0.0) -> None:
    """Refuse, before any slice is sent, what the server would refuse (``ready.limits``), an idle pace too."""
    if pace_s >= (idle := limits.get("idle_s") or np.inf):
        raise UnusableInput(f"a slice every {pace_s:g} s: the server closes a session idle for {idle:g} s")
    pixels, slices = limits.get("pixels_per_slice") or np.inf, limits.get("slices") or np.inf
    for stack in stacks:
        if stack.slices and stack.slices[0].pixels.size > pixels:
            raise UnusableInput(f"stack {stack.name}: slices of {stack.slices[0].pixels.shape} pixels are over "
                                f"the server's limit of {pixels} pixels a slice")
    if sum(len(st.slices) for st in stacks) > slices:
        raise UnusableInput(f"{sum(len(st.slices) for st in stacks)} slices: over the server's limit of {slices}")
    most = limits.get("stacks") or np.inf
    if len(stacks) > most:
        raise UnusableInput(f"{len(stacks)} stacks: over the server's limit of {most} a session; stream the rest in "
                            "another session")
    held = sum(st.slices[0].pixels.size * len(st.slices) for st in stacks if st.slices) * 4 / 2**20
    if held > (limits.get("session_mb") or np.inf):              # the pixels alone, as the server holds them
        raise UnusableInput(f"the stacks' pixels alone take {held:.0f} MB as the server holds them: over its limit of "
                            f"{limits['session_mb']:g} MB a session; stream fewer stacks in each session")
    per_stack = limits.get("stack_slices") or np.inf
    for stack in stacks:
        if len(stack.slices) > per_stack:
            raise UnusableInput(f"stack {stack.name}: {len(stack.slices)} slices, over the server's limit of "
                                f"{per_stack} a stack")


def _slice_message(stack: str, s: ScannerSlice, acquisition_index: int) -> tuple[dict[str, Any], list[bytes]]:
    """The ``slice`` message of ``s`` and its binary frames (pixels, then the mask if any)."""
    dtype = s.pixels.dtype.name if s.pixels.dtype.name in SENT_DTYPES else "float32"
    header = {"type": "slice", "stack": stack, "index": s.index, "acquisition_index": acquisition_index,
              "shape": list(s.pixels.shape), "dtype": dtype,
              "scanner_from_voxel": np.asarray(s.scanner_from_voxel).tolist(), "mask": s.mask is not None}
    frames = [np.ascontiguousarray(s.pixels, np.dtype(dtype).newbyteorder("<")).tobytes()]
    if s.mask is not None:
        frames.append(np.ascontiguousarray(s.mask, np.uint8).tobytes())
    return header, frames
