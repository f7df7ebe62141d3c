"""``/v1/stream``: the real-time WebSocket of Stream v1 (``docs/stream.md``).

One connection is one :class:`~service.streaming.session.StreamSession`. Messages are handled in
the order they arrive, so poses go out in the order the slices came; the stack stage firms the open
stack up in the background (one task per connection, coalescing the slices that arrive meanwhile)
and sends ``update`` messages between the poses. Compute runs in worker threads: poses on
``stream_workers`` threads shared by all sessions, the stack stages on two more (firm-ups, stack
ends) at a lower OS priority (:mod:`~service.streaming.background`), so that no
number of sessions takes more than those cores from ``/v1/predict`` and no pose waits for a stack
stage.

A bad message gets an ``error`` (the problem's RFC 7807 fields, its ``type`` as ``problem_type``)
and changes nothing; only the message's type and size reach the logs, never a pixel.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import numpy as np
from anyio import CapacityLimiter, to_thread
from fastapi import APIRouter, WebSocket
from starlette.datastructures import State
from starlette.websockets import WebSocketDisconnect, WebSocketDisconnected

from service.api.access import UNAUTHORIZED, api_key_ok, origin_ok
from service.api.stream_messages import (DTYPES, STREAM_PATH, is_message, known_fields, parse, slice_header,
                                         text_field)
from service.streaming.messages import (end_stack_messages, error_message, pose_object, summary_message,
                                        update_messages)
from service.core.errors import (
    InternalError,
    InvalidParameter,
    MalformedRequest,
    NotReady,
    RequestTimeout,
    Saturated,
    ServiceError,
    Unauthorized,
)
from service.streaming.answers import SliceAnswer
from service.streaming.frames import SliceFrame
from service.streaming.options import SessionOptions, StreamLimits
from service.streaming.session import StreamSession

router = APIRouter()
T = TypeVar("T")
log = logging.getLogger(__name__)

POLICY_VIOLATION, GOING_AWAY, TRY_AGAIN_LATER = 1008, 1001, 1013


class _Closed(Exception):
    """The client went away, or the session ended."""


class StreamConnection:
    """One client's session: reads messages, answers them, firms stacks up in the background."""

    def __init__(self, ws: WebSocket) -> None:
        self.ws = ws
        state = ws.app.state
        self.settings = state.settings
        self.registry, self.localisers = state.registry, state.localisers
        self.pose_limiter: CapacityLimiter = state.stream_pose_limiter
        self.stages: dict[str, ThreadPoolExecutor] = state.stream_stages
        self.metrics = state.metrics
        self.session: StreamSession | None = None
        self.model = ""
        self.session_id = uuid.uuid4().hex
        self.send_lock = asyncio.Lock()
        self.pending: dict | None = None            # a text message read while a binary frame was due
        self.dirty: set[str] = set()
        self.firming: asyncio.Task | None = None
        self.latencies: list[float] = []
        self.started = time.perf_counter()
        self.last_frame_at = self.started           # when the last binary frame came (a pose's latency starts)
        self.refused = False                        # the last text message was refused: its binary frames are dropped
        self.active_at = self.started               # when the client last sent a message that was answered
        self.counted = False                        # this connection holds one of the session slots

    async def send(self, message: dict) -> None:
        """Send ``message``; :class:`_Closed` where the client has gone (a normal end of a session,
        whichever task finds it first: the messages' loop or the background firm-up), or where it has
        read nothing for ``stream_ping_timeout_s``: a client that stops reading fills the connection's
        buffers, the send waits for it, and neither the pings (their close waits for the same buffer)
        nor the idle limit (it counts while the server reads) would end the session and free its slot."""
        text = json.dumps(message)
        try:
            await asyncio.wait_for(self._send_text(text), self.settings.stream_ping_timeout_s)
        except TimeoutError:
            log.info("stream client stopped reading; session closed", extra={"session_id": self.session_id})
            raise _Closed from None

    async def _send_text(self, text: str) -> None:
        async with self.send_lock:
            try:
                await self.ws.send_text(text)
            except (WebSocketDisconnect, WebSocketDisconnected):
                raise _Closed from None

    def idle_limit_s(self) -> float:
        """How long the client may stay idle: ``stream_idle_s`` once its session has started; before,
        :data:`START_TIMEOUT_S` from the connection (a connection that never starts a session holds
        nothing for long, however often it sends ``auth``)."""
        return self.settings.stream_idle_s if self.session is not None else \
            min(START_TIMEOUT_S, self.settings.stream_idle_s)

    async def receive(self) -> dict:
        """The next frame (``{"text": …}`` or ``{"bytes": …}``); :class:`_Closed` when the client left
        or stayed idle past :meth:`idle_limit_s` (then the server closes with 1001). Only answered
        messages count as activity (a ``ping`` is one; a client that sends nothing but refused ones is
        idle), and a slice's header while its binary frames are awaited."""
        if self.pending is not None:
            frame, self.pending = self.pending, None
            return frame
        limit = self.idle_limit_s()
        since = self.active_at if self.session is not None else self.started
        try:
            frame = await asyncio.wait_for(self.ws.receive(), max(limit - (time.perf_counter() - since), 0.0))
        except WebSocketDisconnected:
            raise _Closed from None
        except TimeoutError:
            await self.send(error_message(RequestTimeout(f"session: idle for {limit:g} s; closing")))
            try:                                    # the close frame waits on the buffers as a send does
                await asyncio.wait_for(self.ws.close(GOING_AWAY), self.settings.stream_ping_timeout_s)
            except TimeoutError:
                pass
            raise _Closed from None
        if frame["type"] == "websocket.disconnect":
            raise _Closed
        return frame

    async def run(self) -> None:
        try:
            while True:
                frame = await self.receive()
                if frame.get("text") is None:
                    if self.refused:                # a refused message's own frames: its error said it all
                        continue
                    size = len(frame.get("bytes") or b"")
                    await self.send(error_message(MalformedRequest(
                        f"binary frame ({size} bytes): not expected here; binary frames follow their slice message")))
                    continue
                self.refused = False
                try:
                    await self.handle(parse(frame["text"]))
                    self.active_at = time.perf_counter()
                except ServiceError as e:
                    log.info("stream message refused", extra={"status": e.status, "session_id": self.session_id})
                    self.refused = True
                    await self.send(error_message(e))
                except (_Closed, WebSocketDisconnect):
                    raise
                except Exception:  # noqa: BLE001 - a server fault ends one message, never the session
                    log.exception("stream message failed", extra={"session_id": self.session_id})
                    self.refused = True
                    await self.send(error_message(InternalError(f"session {self.session_id}: the server could "
                                                                "not answer this message")))
        except (_Closed, WebSocketDisconnect):
            pass
        finally:
            if self.firming is not None:
                self.firming.cancel()
            if self.counted:
                self.ws.app.state.stream_sessions -= 1
            log.info("stream session", extra={"session_id": self.session_id, "route": STREAM_PATH,
                                               "model": self.model, "n_slices": len(self.latencies),
                                               "duration_ms": round((time.perf_counter() - self.started) * 1e3, 1)})

    async def handle(self, msg: dict) -> None:
        kind = msg["type"]
        if kind == "auth" and self.session is None:       # a key sent both ways: the header's was checked
            return
        if kind == "auth":                                 # answered, and so no sign of life (the idle limit)
            raise InvalidParameter("auth: the session has started; a key is sent once, before start")
        if kind == "ping":                                 # a sign of life between stacks (the idle limit)
            known_fields(msg, kind)
            return await self.send({"type": "pong"})
        if kind == "start":
            return await self.start(msg)
        if self.session is None and kind in ("slice", "end_stack", "end"):
            raise InvalidParameter(f"{kind}: no session yet; send a start message first")
        if kind == "slice":
            return await self.slice(msg)
        if kind == "end_stack":
            return await self.end_stack(text_field(known_fields(msg, kind), "stack", "end_stack"))
        if kind == "end":
            known_fields(msg, kind)
            await self.settle()
            summary = await self.in_background("end_stack", self.session.summary)
            await self.send(summary_message(summary, self.started, self.latencies))
            await self.ws.close(1000)
            raise _Closed
        raise InvalidParameter(f"type: unknown message type {kind!r} (auth, start, slice, end_stack, end, ping)")

    async def start(self, msg: dict) -> None:
        if self.session is not None:
            raise InvalidParameter("start: the session has started already")
        if self.registry is None:
            raise NotReady("model: the models are still loading")
        options = SessionOptions.from_start(msg)
        model = self.registry.resolve(options.model)
        estimator = self.registry.get(model)
        state = self.ws.app.state
        if (busy := sessions_full(state)) is not None:
            await self.send(error_message(busy, retry_after_s=self.settings.retry_after_s))
            await self.ws.close(TRY_AGAIN_LATER)
            raise _Closed
        localiser = self.localisers.default()             # none: slices bring masks
        limits = StreamLimits.of(self.settings)
        self.session = StreamSession(estimator, localiser, limits, options)
        self.model = model
        state.stream_sessions += 1                  # a slot from the session's start (once it stands), not the connection's
        self.counted = True
        info = estimator.info
        await self.send({"type": "ready", "session_id": self.session_id,
                         "model": info.reference(model),
                         "mc_samples": options.mc_samples, "variance_threshold": self.session.threshold,
                         "max_expected_error_mm": self.session.max_expected_error_mm,
                         "localiser": localiser is not None,
                         "localiser_model": None if localiser is None else localiser.provenance(),
                         "limits": {"slices": limits.max_slices, "stacks": limits.max_stacks,
                                    "stack_slices": limits.max_stack_slices,
                                    "pixels_per_slice": limits.max_pixels,
                                    "session_mb": limits.max_bytes / 2**20, "idle_s": self.settings.stream_idle_s}})

    async def slice(self, msg: dict) -> None:
        frame = await self.read_slice(msg)
        answer: SliceAnswer = await to_thread.run_sync(self.session.add_slice, frame, limiter=self.pose_limiter)
        self.metrics.observe_slices(self.model, [answer.prediction.reasons[answer.row]])
        latency = (time.perf_counter() - self.last_frame_at) * 1e3       # from the slice's last frame
        self.latencies.append(latency)
        await self.send({"type": "pose", **pose_object(answer, latency_ms=round(latency, 2))})
        self.firm_up(frame.stack)

    async def read_slice(self, msg: dict) -> SliceFrame:
        """The slice message's fields (:func:`~service.api.stream_messages.slice_header`, checked before
        anything is decoded) and its binary frame(s)."""
        head = slice_header(msg, self.settings.stream_max_pixels)
        n0, n1 = head.shape
        idle_since, self.active_at = self.active_at, time.perf_counter()   # its frames may take a while
        try:
            pixels = np.frombuffer(await self.binary(np.dtype(DTYPES[head.dtype]).itemsize * n0 * n1, "pixels"),
                                   DTYPES[head.dtype]).reshape(head.shape)
            mask = None
            if head.with_mask:
                mask = np.frombuffer(await self.binary(n0 * n1, "mask"), np.uint8).reshape(head.shape) > 0
        finally:                           # the slice's answer, not its header, is the sign of life
            self.active_at = idle_since
        return SliceFrame(head.stack, head.index, pixels.astype(np.float32), head.scanner_from_voxel, mask,
                          head.acquisition_index)

    async def binary(self, size: int, what: str) -> bytes:
        """The slice's ``what`` binary frame of ``size`` bytes. A text frame in its place is the
        client's next message where it is one (read next), else the slice's frame sent as text
        (dropped with the slice): one error either way."""
        frame = await self.receive()
        data = frame.get("bytes")
        if data is None:
            if is_message(frame.get("text") or ""):
                self.pending = frame
            raise InvalidParameter(f"slice: its {what} binary frame was due, a text frame came; the slice is dropped")
        self.last_frame_at = time.perf_counter()
        if len(data) != size:
            raise InvalidParameter(f"slice: its {what} frame has {len(data)} bytes, {size} were due "
                                   "(shape x dtype size); the slice is dropped")
        return data

    async def in_background(self, stage: str, fn: Callable[..., T], *args: object) -> T:
        """``fn(*args)`` on the thread of ``stage`` (``firm_up`` or ``end_stack``; a lower OS priority
        than the poses'; a stack's end never waits behind the firm-ups of other sessions)."""
        return await asyncio.get_running_loop().run_in_executor(self.stages[stage], fn, *args)

    def firm_up(self, stack: str) -> None:
        """Run the stack stage on ``stack`` in the background (one run at a time; slices that arrive
        meanwhile are taken by the next run); ``svrnet-mrd`` keeps the same queue on a thread
        (:meth:`service.mrd.connection.MrdConnection.firm_up`)."""
        self.dirty.add(stack)
        if self.firming is None or self.firming.done():
            self.firming = asyncio.create_task(self._firm_up_loop())

    async def _firm_up_loop(self) -> None:
        while self.dirty:
            stack = self.dirty.pop()
            try:
                updates = await self.in_background("firm_up", self.session.firm_up, stack)
                for message in update_messages(updates):
                    await self.send(message)
            except _Closed:                         # the client has gone: nothing to firm up for
                self.dirty.clear()
                return
            except Exception:  # noqa: BLE001 - a background stage must not end the session; the stack's end says more
                log.warning("stream firm-up failed", exc_info=True, extra={"session_id": self.session_id})

    async def settle(self, stack: str | None = None) -> set[str]:
        """Wait for the background stage's running firm-up (its updates go out before what follows).
        The queued firm-ups are taken out of the queue: that of ``stack`` (every one when None) is
        dropped, its end runs the stage anyway; the other stacks' are returned, for the caller to
        queue again once it is done (:meth:`end_stack`), so that one stack's end neither waits for
        nor loses another's."""
        others = self.dirty - {stack} if stack is not None else set()
        self.dirty.clear()
        if self.firming is not None:
            await asyncio.gather(self.firming, return_exceptions=True)
        return others

    async def end_stack(self, stack: str) -> None:
        others = await self.settle(stack)
        try:
            answer = await self.in_background("end_stack", self.session.end_stack, stack)
            for message in end_stack_messages(answer):
                await self.send(message)
        finally:                                    # a refused end changes nothing: the others' firm-ups run
            for other in others:
                self.firm_up(other)


AUTH_TIMEOUT_S = 10.0
"""How long a connection without a key in its headers may take to send its ``auth`` message: until
then it holds no session slot, so it is not left waiting as long as an idle session."""
START_TIMEOUT_S = 10.0
"""How long a connection may take to start its session (its ``start`` answered): until then it holds
no session slot, and a connection that never starts one is closed (1001) rather than left open."""


def sessions_full(state: State) -> Saturated | None:
    """503 when ``stream_max_sessions`` sessions have started and not ended."""
    if state.stream_sessions >= state.settings.stream_max_sessions:
        return Saturated(f"session: {state.settings.stream_max_sessions} stream sessions are open; try again later")
    return None


@router.websocket(STREAM_PATH)
async def stream(ws: WebSocket) -> None:
    """Stream v1: one session per connection (see the module)."""
    state = ws.app.state
    if not origin_ok(state.settings, {k.lower(): v for k, v in ws.headers.items()}):
        await ws.close(POLICY_VIOLATION)             # before the handshake: the page gets an HTTP 403
        return
    await ws.accept()
    keys = state.settings.key_set()
    if not api_key_ok(keys, ws.headers.get("authorization"), ws.headers.get("x-api-key")):
        try:
            first = parse(await asyncio.wait_for(ws.receive_text(), min(AUTH_TIMEOUT_S, state.settings.stream_idle_s)))
        except (ServiceError, TimeoutError, WebSocketDisconnect, KeyError, RuntimeError):
            first = {}
        key = first.get("api_key") if first.get("type") == "auth" else None
        if not (isinstance(key, str) and api_key_ok(keys, f"Bearer {key}", None)):
            await ws.send_text(json.dumps(error_message(Unauthorized(UNAUTHORIZED))))
            await ws.close(POLICY_VIOLATION)
            return
    if (busy := sessions_full(state)) is not None:          # refused at once; the slot is taken at `start`
        await ws.send_text(json.dumps(error_message(busy, retry_after_s=state.settings.retry_after_s)))
        await ws.close(TRY_AGAIN_LATER)
        return
    await StreamConnection(ws).run()
