"""One MRD connection: config and XML header, images in; each image back with its pose, TEXT messages
with updates, each stack's final poses and the session's summary.

The messages are those of Gadgetron's external language interface and Siemens FIRE's
python-ismrmrd-server, read and written by ``ismrmrd``'s :class:`~ismrmrd.ProtocolDeserializer` and
:class:`~ismrmrd.ProtocolSerializer`:

* ``CONFIG_TEXT`` holding a JSON object sets the session's options (``model``, ``mc_samples``,
  ``variance_threshold``, ``max_expected_error_mm``, as ``/v1/predict`` and Stream v1's ``start``); any
  other config (a FIRE config name, a Gadgetron XML configuration) is accepted and ignored;
* ``HEADER``: ``encoding[0].encodingLimits.slice.maximum + 1``, when present, is the number of slices
  of each series; the series ends (``end_stack``) as soon as that many distinct slices have arrived;
* ``IMAGE``: stack = ``image_series_index`` (a series that arrives again after it ended is a new stack,
  ``"<series>.<n>"``), index = ``slice``; the order of arrival is the acquisition order;
* ``CLOSE``: the open stacks end, the summary follows, then the server's ``CLOSE``.

Each answer is written as soon as it exists. Between images, the stack stage firms the open series up
in a background thread of the connection; slices it moves by more than 1 mm go out as TEXT ``update``
messages (Stream v1's), as do earlier series' slices moved by a series' end. A message that cannot be used gets a TEXT error (RFC 7807
fields) and the connection goes on, except where the stream cannot be followed any more (an image
over the pixel limit, an unknown message, an unreadable image): then the error is followed by
``CLOSE``. Only message kinds and counts reach the log, never pixels, headers or meta attributes.
"""

from __future__ import annotations

import json
import logging
import struct
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, wait
from dataclasses import dataclass, field
from typing import Any, BinaryIO

import ismrmrd
from ismrmrd.serialization import ConfigText, ISMRMRDMessageID

from service.streaming.messages import (end_stack_messages, error_message, pose_object, summary_message,
                                        update_messages)
from service.core.errors import (InternalError, InvalidParameter, PayloadTooLarge, RequestTimeout, ServiceError,
                                 UnusableImage)
from service.mrd.images import slice_from_image, with_pose
from service.mrd.protocol import (BYTES_PER_VALUE, MAX_TEXT_BYTES, BoundedReader, ProtocolBroken, in_mrd_terms,
                                 read_past_unusable_image, skip_raw_message)
from service.streaming.frames import IncompleteStack, SliceFrame, SlicesDropped
from service.streaming.answers import SessionSummary
from service.streaming.background import background_executor
from service.streaming.coverage import Coverage
from service.streaming.options import SessionOptions, StreamLimits
from service.streaming.session import StreamSession

log = logging.getLogger(__name__)

RAW_DATA = {ISMRMRDMessageID.ACQUISITION: "acquisition", ISMRMRDMessageID.WAVEFORM: "waveform",
            ISMRMRDMessageID.NDARRAY: "ndarray"}
KNOWN = {int(m) for m in ISMRMRDMessageID} - {int(ISMRMRDMessageID.UNPEEKED)}
SessionFactory = Callable[[SessionOptions], StreamSession]


@dataclass
class SeriesState:
    """Where a series stands: its current stack's name, the slices it has, how often it has ended."""

    stack: str
    slices: set[int] = field(default_factory=set)
    passes: int = 1


class MrdConnection:
    """The messages of one connection, answered in order (see the module)."""

    def __init__(self, reader: BinaryIO, writer: BinaryIO, new_session: SessionFactory, limits: StreamLimits,
                 idle_s: float | None = None) -> None:
        self.reader = BoundedReader(reader, max(limits.max_pixels * BYTES_PER_VALUE, MAX_TEXT_BYTES))
        self.writer = writer
        self.incoming = ismrmrd.ProtocolDeserializer(self.reader)  # type: ignore[arg-type]
        self.outgoing = ismrmrd.ProtocolSerializer(writer)
        self.new_session, self.limits = new_session, limits
        self.session: StreamSession | None = None
        self.refused_config: ServiceError | None = None
        """The session's config, when it was refused: images are then refused too, not posed with defaults."""
        self.slices_per_series: int | None = None
        self.series: dict[int, SeriesState] = {}
        self.counts = {"images": 0, "refused": 0, "stacks": 0}
        self.started, self.latencies = time.perf_counter(), []
        self.ignored: set[str] = set()
        self.broken = False
        """Whether the connection ended inside a message (its rest unread)."""
        self.idle_s, self.active_at = idle_s, time.monotonic()
        """How long a connection may go without a message the server takes (None: no limit), and when
        it last took one: ignored and refused messages do not keep a session slot."""
        self.send_lock, self.stage_lock = threading.Lock(), threading.Lock()
        self.stage = background_executor("svrnet-mrd-stage")
        self.dirty: set[str] = set()
        self.firming: Future | None = None

    # -- the loop -------------------------------------------------------------------------------------------
    def run(self) -> None:
        """Answer messages until the client's ``CLOSE`` (answered by the summary and ``CLOSE``), the end
        of its stream (no answer), or a broken stream (an error, then ``CLOSE``)."""
        t0 = time.perf_counter()
        outcome = "closed"
        try:
            while self.step():
                pass
            self.finish()
        except ProtocolBroken as broken:
            outcome, self.broken = "broken", True
            self.close_with(broken.error)
        except TimeoutError:
            outcome, self.broken = "idle", True
            self.close_with(RequestTimeout("connection: no message for too long; the server closes it"))
        except (EOFError, ConnectionError):
            outcome = "client gone"
        finally:
            self.settle()
            self.stage.shutdown()
        log.info("mrd connection ended: %s", outcome,
                 extra={"n_slices": self.counts["images"], "n_refused": self.counts["refused"],
                        "n_stacks": self.counts["stacks"],
                        "duration_ms": round((time.perf_counter() - t0) * 1e3, 1)})

    def step(self) -> bool:
        """Read and answer one message; ``False`` at the client's ``CLOSE``."""
        if self.idle_s is not None and time.monotonic() - self.active_at > self.idle_s:
            raise ProtocolBroken(RequestTimeout(f"connection: no message the server takes for {self.idle_s:g} s "
                                                "(ignored and refused ones do not count); the server closes it"))
        self.reader.next_message()
        kind = self.incoming.peek()
        if kind not in KNOWN:
            raise ProtocolBroken(InvalidParameter(f"message: unknown MRD message id {kind}"))
        if kind == ISMRMRDMessageID.IMAGE:
            if self.check_announced_image():
                return True
        elif kind in RAW_DATA:
            self.skip_raw(kind)
            return True
        try:
            message = next(self.incoming.deserialize(), None)
        except (EOFError, OSError):
            raise
        except PayloadTooLarge as too_large:
            raise ProtocolBroken(too_large) from None
        except Exception as exc:  # noqa: BLE001 - ismrmrd's parsers raise many kinds; the type is what we log
            log.info("mrd message unreadable", extra={"error_type": type(exc).__name__})
            kind_of = UnusableImage if kind == ISMRMRDMessageID.IMAGE else InvalidParameter
            problem = kind_of(f"{ISMRMRDMessageID(kind).name.lower()}: the message could not be parsed")
            if kind in (ISMRMRDMessageID.HEADER, ISMRMRDMessageID.CONFIG_TEXT, ISMRMRDMessageID.TEXT,
                        ISMRMRDMessageID.CONFIG_FILE):
                self.send_error(problem)            # read whole before parsing: the stream is still in step
                return True
            raise ProtocolBroken(problem) from None
        if message is None:
            return False
        self.dispatch(kind, message)
        return True

    def skip_raw(self, kind: int) -> None:
        """Read past a raw-data message, bounded by its head before its data (``ismrmrd`` would allocate
        what the head announces first), and say once per kind that it is ignored."""
        try:
            skip_raw_message(kind, self.reader)
        except PayloadTooLarge as too_large:
            raise ProtocolBroken(too_large) from None
        except struct.error:
            raise ProtocolBroken(InvalidParameter(f"{RAW_DATA[ISMRMRDMessageID(kind)]}: the message could not "
                                                  "be parsed")) from None
        self.incoming = ismrmrd.ProtocolDeserializer(self.reader)  # type: ignore[arg-type]  # forgets the peeked id
        name = RAW_DATA[ISMRMRDMessageID(kind)]
        if name not in self.ignored:                      # said once per kind: raw data come by the thousand
            self.ignored.add(name)
            self.send_error(InvalidParameter(f"{name}: svrnet-mrd takes reconstructed images; "
                                             f"{name} messages are ignored"))

    def check_announced_image(self) -> bool:
        """:func:`~service.mrd.protocol.read_past_unusable_image` on the image whose header ``peek`` has
        read: ``True`` where it was of a shape the stream cannot use, read past and answered with its
        error (the session goes on); the connection ends where it announces more than the limits."""
        problem = read_past_unusable_image(self.reader, self.limits.max_pixels)
        if problem is None:
            return False
        self.incoming = ismrmrd.ProtocolDeserializer(self.reader)  # type: ignore[arg-type]  # forgets the peeked id
        self.counts["images"] += 1
        self.counts["refused"] += 1
        self.send_error(in_mrd_terms(problem[0]), series=problem[1], slice_index=problem[2])
        return True

    def dispatch(self, kind: int, message: Any) -> None:
        if kind == ISMRMRDMessageID.IMAGE:
            self.on_image(message)
        elif kind == ISMRMRDMessageID.HEADER:
            self.on_header(message)
        elif kind == ISMRMRDMessageID.CONFIG_TEXT:
            self.on_config(message)
        elif kind == ISMRMRDMessageID.CONFIG_FILE:
            log.info("mrd config file name ignored")
        else:
            log.info("mrd text message ignored")

    # -- messages ---------------------------------------------------------------------------------------------
    def on_config(self, text: ConfigText) -> None:
        """JSON options of the session (before its first image); other config texts are ignored."""
        if not text.lstrip().startswith("{"):
            log.info("mrd config text ignored")
            return
        if self.counts["images"]:
            self.send_error(InvalidParameter("config: options arrive before the first image; these are ignored"))
            return
        try:
            options = SessionOptions.from_json(text, "config")
            self.session = self.new_session(options)      # an unknown model is named now, not at each image
            self.refused_config, self.active_at = None, time.monotonic()
        except ServiceError as bad:
            self.session, self.refused_config = None, bad
            self.send_error(bad)

    def on_header(self, header: ismrmrd.xsd.ismrmrdHeader) -> None:
        """The number of slices of each series, from the first encoding's slice limit (when it gives
        one of at least two slices; an absent, empty or negative maximum says nothing, and each
        series' stack then ends with the series)."""
        encoding = header.encoding[0] if header.encoding else None
        limit = None if encoding is None or encoding.encodingLimits is None else encoding.encodingLimits.slice
        maximum = None if limit is None else limit.maximum
        self.slices_per_series = int(maximum) + 1 if maximum is not None and int(maximum) >= 1 else None
        self.active_at = time.monotonic()

    def on_image(self, image: ismrmrd.Image) -> None:
        received = time.perf_counter()
        self.counts["images"] += 1
        series_index = int(image.image_series_index)
        series = self.series.setdefault(series_index, SeriesState(str(series_index)))
        try:
            self.check_slice(int(image.slice))
            session = self.open_session()
            pixels, scanner_from_voxel = slice_from_image(image)
            answer = session.add_slice(SliceFrame(series.stack, int(image.slice), pixels, scanner_from_voxel))
        except ServiceError as refused:
            self.counts["refused"] += 1
            self.send_error(in_mrd_terms(refused), series=series_index, slice_index=int(image.slice))
            return
        except Exception as fault:  # noqa: BLE001 - a fault of the server: the type goes to the log, the session goes on
            log.error("mrd image failed", extra={"error_type": type(fault).__name__})
            self.send_error(InternalError("image: the server failed on this image"), series_index, int(image.slice))
            return
        self.latencies.append((time.perf_counter() - received) * 1e3)
        pose = pose_object(answer, latency_ms=round(self.latencies[-1], 2))
        self.send(with_pose(image, pose))
        series.slices.add(int(image.slice))
        if self.slices_per_series is not None and len(series.slices) >= self.slices_per_series:
            self.end_series(series_index)
        else:
            self.firm_up(series.stack)
        self.active_at = time.monotonic()              # after the server's own work: that is not the client idle

    def check_slice(self, index: int) -> None:
        """Refuse a slice the header's slice count leaves out (MRD counts slices from 0): the series
        would wait for a slice that never comes, and end without it."""
        if self.slices_per_series is not None and index >= self.slices_per_series:
            raise InvalidParameter(f"slice.index: {index} is beyond the header's {self.slices_per_series} slices "
                                   f"(encodingLimits.slice.maximum {self.slices_per_series - 1}; slices count from 0)")

    def firm_up(self, stack: str) -> None:
        """Run the stack stage on ``stack`` in this connection's background thread (one run at a time;
        the slices that arrive meanwhile are taken by the next run); moved slices go out as updates.
        The same queue as :meth:`service.api.stream.StreamConnection.firm_up`, on a thread here
        (a connection is a thread) where the WebSocket's is a task."""
        with self.stage_lock:
            self.dirty.add(stack)
            if self.firming is None:
                self.firming = self.stage.submit(self._firm_up_loop)

    def _firm_up_loop(self) -> None:
        while True:
            with self.stage_lock:
                if not self.dirty:
                    self.firming = None
                    return
                stack = self.dirty.pop()
            try:
                updates = self.open_session().firm_up(stack)
                for message in update_messages(updates):
                    self.send_text(message)
            except Exception as fault:  # noqa: BLE001 - a background stage must not end the session
                log.warning("mrd firm-up failed", extra={"error_type": type(fault).__name__})

    def settle(self, stack: str | None = None) -> set[str]:
        """Wait for the background stage's running firm-up (its updates go out before what follows);
        the queued firm-ups are taken out of the queue: that of ``stack`` (every one when None) is
        dropped, the other stacks' returned for the caller to queue again (:meth:`end_series`), as
        :meth:`service.api.stream.StreamConnection.settle` does."""
        with self.stage_lock:
            others = self.dirty - {stack} if stack is not None else set()
            self.dirty.clear()
            running = self.firming
        if running is not None:
            wait([running])
        return others

    def open_session(self) -> StreamSession:
        """The session: the config's, else the defaults' when no config came. After a refused config
        (and no valid one before the first image) every image is refused, as the stream refuses slices
        after a refused ``start``: poses made with options the client did not ask for would pass for
        its own."""
        if self.session is None and self.refused_config is not None:
            raise InvalidParameter(f"config was refused ({self.refused_config.detail}); images are not posed "
                                   "until the connection starts again with a valid config")
        if self.session is None:
            self.session = self.new_session(SessionOptions())
        return self.session

    def end_series(self, series_index: int) -> None:
        """End the series' stack (answered by its final poses) and start its next pass afresh; where its
        end dropped slices off its even spacing, the series stays open for them instead (it ends when
        they come again, or at close without them)."""
        series = self.series.pop(series_index)
        others = self.settle(series.stack)
        next_pass = SeriesState(f"{series_index}.{series.passes + 1}", passes=series.passes + 1)
        try:
            answer = self.stage.submit(self.open_session().end_stack, series.stack).result()   # at the stages' priority
        except ServiceError as failed:
            if isinstance(failed, SlicesDropped):
                series.slices -= set(failed.indices)
                next_pass = series
                failed = InvalidParameter(f"series {series_index}: the slices {failed.indices[:10]} lie off the even "
                                          "spacing of its other slices along their normal and are dropped from it; it "
                                          "ends once they come again where they belong, or at close without them")
            elif series.passes > 1 and isinstance(failed, IncompleteStack):
                failed = InvalidParameter(
                    f"series {series_index}: the slices {sorted(series.slices)[:10]} came after the series had ended; "
                    f"they make a pass of their own (stack {series.stack!r}), which ends as a stack only with most "
                    "of its slices: their immediate poses are their answer (the summary's unfinished lists the pass)")
            self.send_error(in_mrd_terms(failed), series=series_index)
        except Exception as fault:  # noqa: BLE001 - as in on_image
            log.error("mrd stack failed", extra={"error_type": type(fault).__name__})
            self.send_error(InternalError("stack: the server failed on this series"), series=series_index)
        else:
            self.counts["stacks"] += 1
            for message in end_stack_messages(answer):      # earlier stacks' slices it moved, then its own
                self.send_text(message)
        for other in others:                               # the other series' firm-ups, still to come
            self.firm_up(other)
        self.series[series_index] = next_pass

    def finish(self) -> None:
        """The client closed: end the open stacks, send the summary (an empty one where no session
        was opened: every image refused with its options), close."""
        for series_index, series in list(self.series.items()):
            while series.slices:
                left = len(series.slices)
                self.end_series(series_index)
                if self.series.get(series_index) is not series or len(series.slices) >= left:
                    break       # ended (or failed); else its end dropped slices, which cannot come now: again
        self.settle()
        summary = self.session.summary() if self.session is not None else \
            SessionSummary([], Coverage(0.0, 0.0, measured=False), 0, {})    # no session opened (its options refused)
        self.send_text(summary_message(summary, self.started, self.latencies))
        self.outgoing.close()

    # -- answers ---------------------------------------------------------------------------------------------------
    def send(self, message: Any) -> None:
        with self.send_lock:                               # the background stage writes updates too
            self.outgoing.serialize(message)
            self.writer.flush()

    def send_text(self, body: dict) -> None:
        self.send(json.dumps(body))

    def close_with(self, error: ServiceError) -> None:
        """The session's stages settled, then the error and ``CLOSE`` (:meth:`say_last`)."""
        self.settle()
        self.say_last(error_message(error))

    def stop(self, error: ServiceError, retry_after_s: int) -> None:
        """Tell the client that the server stops (:meth:`say_last`, with ``retry_after_s``); runs on the
        server's thread while the session's own may be blocked reading."""
        self.say_last(error_message(error, retry_after_s=retry_after_s))

    def say_last(self, error: dict) -> None:
        """The ``error`` message, then ``CLOSE``; a client that is gone or does not read is not told."""
        try:
            self.send_text(error)
            with self.send_lock:
                self.outgoing.close()
        except (OSError, TimeoutError, ConnectionError):
            pass

    def send_error(self, error: ServiceError, series: int | None = None, slice_index: int | None = None) -> None:
        """A TEXT with Stream v1's ``error`` (the problem's RFC 7807 fields, its ``type`` as
        ``problem_type``), and the image's series and slice when it names one."""
        extra = {k: v for k, v in (("image_series_index", series), ("slice", slice_index)) if v is not None}
        self.send_text(error_message(error, **extra))


def refuse(writer: BinaryIO, error: ServiceError, **extra: object) -> None:
    """Answer a connection that is not taken: the error as a TEXT, then ``CLOSE``."""
    outgoing = ismrmrd.ProtocolSerializer(writer)
    outgoing.serialize(json.dumps(error_message(error, **extra)))
    outgoing.close()
