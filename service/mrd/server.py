"""``svrnet-mrd``: a TCP server speaking the MRD streaming protocol (Gadgetron's external language
interface, Siemens FIRE's python-ismrmrd-server) in front of the streaming core of ``/v1/stream``.

Each connection is one :class:`~service.streaming.session.StreamSession` in a thread of its own
(:class:`~service.mrd.connection.MrdConnection` says what it answers). Settings are the service's
``SVRNET_*`` variables: the models (``SVRNET_MODELS_DIR``, ``SVRNET_DEFAULT_MODEL``,
``SVRNET_ONNX_THREADS``), the localiser (``SVRNET_LOCALISERS_DIR``: MRD images carry no brain mask,
so one must be installed) and the stream's limits (``SVRNET_STREAM_MAX_SESSIONS``,
``SVRNET_STREAM_MAX_SLICES``, ``SVRNET_STREAM_MAX_PIXELS``, ``SVRNET_STREAM_IDLE_S``); options:

* ``--host`` (default ``SVRNET_HOST``) and ``--port`` (default 9002, FIRE's);
* ``--max-sessions``, ``--idle-s``: override the stream settings for this server.

SIGTERM or Ctrl-C stops the server; open connections end with it.

Example:
    >>> parser().parse_args(["--port", "9100"]).port
    9100
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import socket
import socketserver
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from service.core import logging as service_logging
from service.core.errors import RequestTimeout, Saturated, UnusableModelFile
from service.core.listening import listen_problem
from service.core.settings import Settings, load_settings, warn_unknown_variables
from service.core.threads import limit_blas_threads
from service.inference.registry import ModelRegistry
from service.mrd.connection import MrdConnection, SessionFactory, refuse
from service.mrd.outbox import Outbox
from service.preprocess.localise import Localiser, Localisers
from service.streaming.options import SessionOptions, StreamLimits
from service.streaming.session import StreamSession

log = logging.getLogger(__name__)

LINGER_S, LINGER_CHUNKS = 2.0, 256
"""After a broken stream: how long in all, and how many 64 KiB chunks at most, the server drains
before it closes."""
DEFAULT_PORT = 9002
"""The port of FIRE's python-ismrmrd-server, which scanners' FIRE configurations name by default."""
DEFAULT_HOST = "127.0.0.1"
"""Where svrnet-mrd listens unless ``--host`` says otherwise: MRD carries no API key, so the port
opens to a network only where the operator names that network, not with the HTTP API's
``SVRNET_HOST``."""
FIRST_BYTES_S = 10.0
"""How long a new connection may send nothing before the server closes it, holding no session slot
meanwhile: a scanner sends its configuration at once; a peer that connects and waits (or a port
probe) would otherwise keep a slot for the whole idle limit, and a few such the scanners out."""
STOP_GRACE_S = 2.0
"""How long each open session's last answers (its stop error and ``CLOSE``) may take to go out when the
server stops."""


def session_factory(registry: ModelRegistry, localiser: Localiser | None, limits: StreamLimits) -> SessionFactory:
    """A new :class:`StreamSession` for each connection's options (:class:`NotFound` names an unknown model)."""
    def new_session(options: SessionOptions) -> StreamSession:
        return StreamSession(registry.get(options.model), localiser, limits, options)
    return new_session


@dataclass(frozen=True)
class ServerLimits:
    """What the server takes at once: connections, and how long one may stay silent."""

    max_sessions: int = 32
    idle_s: float = 300.0


class MessageDeadlineReader:
    """The connection's bytes with one deadline per message: from when the server waits for a
    message (:meth:`next_message`) to its last byte, at most ``seconds``. A socket's own timeout
    bounds each ``recv`` alone, so a client that sends a byte now and then would hold its session
    slot for ever.

    Example:
        >>> a, b = socket.socketpair()
        >>> _ = b.sendall(b"abcdef")
        >>> r = MessageDeadlineReader(a, seconds=0.2)
        >>> r.next_message(); r.read(4), r.read(2)
        (b'abcd', b'ef')
        >>> r.next_message(); r.read(1)
        Traceback (most recent call last):
        ...
        TimeoutError: the message did not arrive within 0.2 s
    """

    def __init__(self, sock: socket.socket, seconds: float, chunk: int = 1 << 16) -> None:
        self.sock, self.seconds, self.chunk = sock, seconds, chunk
        self.buffer = bytearray()
        self.deadline = time.monotonic() + seconds

    def next_message(self) -> None:
        """A new message is awaited: its deadline starts now."""
        self.deadline = time.monotonic() + self.seconds

    def read(self, n: int) -> bytes:
        while len(self.buffer) < n:
            left = self.deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"the message did not arrive within {self.seconds:g} s")
            self.sock.settimeout(left)
            try:
                data = self.sock.recv(max(self.chunk, n - len(self.buffer)))
            except TimeoutError:
                raise TimeoutError(f"the message did not arrive within {self.seconds:g} s") from None
            if not data:                                 # the client's end of the stream
                break
            self.buffer += data
        out = bytes(self.buffer[:n])
        del self.buffer[:n]
        return out


class MrdHandler(socketserver.StreamRequestHandler):
    """One connection: a session when a slot is free, else an error with ``retry_after_s`` and ``CLOSE``."""

    server: "MrdServer"
    rbufsize = 1 << 16
    disable_nagle_algorithm = True

    def handle(self) -> None:
        server = self.server
        if not server.slots.acquire(blocking=False):
            self.refuse_busy()
            return
        server.slots.release()         # one is free: taken once the client speaks (a silent peer holds none)
        if not self.first_bytes(min(FIRST_BYTES_S, server.limits.idle_s or FIRST_BYTES_S)):
            return
        self.connection.settimeout(server.limits.idle_s)
        if not server.slots.acquire(blocking=False):
            self.refuse_busy()
            return
        outbox: Outbox | None = None
        connection = None
        try:
            outbox = Outbox(self.connection, server.limits.idle_s, server.stream_limits.max_bytes)
            reader = MessageDeadlineReader(self.connection, server.limits.idle_s)
            connection = MrdConnection(reader, outbox, server.new_session, server.stream_limits, server.limits.idle_s)
            with server.live_lock:
                server.live[connection] = outbox
            connection.run()
            outbox.drain(server.limits.idle_s)          # the answers still queued, as far as the client reads
        finally:
            with server.live_lock:
                server.live.pop(connection, None)
            if outbox is not None:
                outbox.drain(0.0)                       # after a failure too: no writer thread left behind
            server.slots.release()
        if connection.broken:
            self.linger()

    def refuse_busy(self) -> None:
        """Every session slot is taken: the client is told when to try again."""
        server = self.server
        log.warning("mrd connection refused: every session slot is taken")
        busy = Saturated(f"session: {server.limits.max_sessions} MRD sessions are open; try again later")
        try:
            refuse(self.wfile, busy, retry_after_s=server.retry_after_s)
        except OSError:                 # the client left first: nothing to tell it
            log.info("mrd refused connection closed before its answer")

    def first_bytes(self, within_s: float) -> bool:
        """Whether the client sends something within ``within_s`` (looked at, not read). A connection
        closed first is a probe (logged at debug); a silent one is told it waited too long, and closed
        (as an idle session is), before it takes a slot."""
        self.connection.settimeout(within_s)
        try:
            return bool(self.connection.recv(1, socket.MSG_PEEK)) or self.probed()
        except TimeoutError:
            log.info("mrd connection sent nothing within %g s", within_s)
            try:
                refuse(self.wfile, RequestTimeout(f"connection: no message for too long ({within_s:g} s before the "
                                                  "first); the server closes it"))
            except OSError:
                pass
        except OSError:                               # reset before a byte: a probe too
            return self.probed()
        return False

    def probed(self) -> bool:
        """A connection closed before its first byte (a port check): logged at debug; False."""
        log.debug("mrd connection closed before its first message")
        return False

    def linger(self) -> None:
        """Half-close and drain what the client still sends (bounded), so that closing with unread data
        does not reset the connection before the client has read the error and ``CLOSE``."""
        deadline = time.monotonic() + LINGER_S       # in all: a byte every second must not hold the thread
        try:
            self.wfile.flush()
            self.connection.shutdown(socket.SHUT_WR)
            for _ in range(LINGER_CHUNKS):
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self.connection.settimeout(left)
                if not self.connection.recv(1 << 16):
                    break
        except OSError:
            pass


class MrdServer(socketserver.ThreadingTCPServer):
    """The threaded TCP server; each connection runs in a daemon thread of its own."""

    daemon_threads = True
    allow_reuse_address = True
    request_queue_size = 128
    """The listen backlog: a burst of scanner connections waits for ``accept`` (socketserver's 5 made
    the kernel reset connections of a burst far below the session slots); past the slots each gets
    its 503 error."""

    def __init__(self, address: tuple[str, int], new_session: SessionFactory, stream_limits: StreamLimits,
                 limits: ServerLimits = ServerLimits(), retry_after_s: int = 2) -> None:
        self.new_session, self.stream_limits, self.limits = new_session, stream_limits, limits
        self.retry_after_s = retry_after_s
        self.slots = threading.BoundedSemaphore(limits.max_sessions)
        self.live: dict[MrdConnection, Outbox] = {}
        self.live_lock = threading.Lock()
        if ":" in address[0]:              # an IPv6 address (``::1``, ``::``): socketserver's family is IPv4's
            self.address_family = socket.AF_INET6
        super().__init__(address, MrdHandler)

    @property
    def port(self) -> int:
        return int(self.server_address[1])

    def tell_stopping(self, grace_s: float = STOP_GRACE_S) -> int:
        """Tell every open session that the server stops (a 503 ``error`` with ``retry_after_s``, then
        ``CLOSE``), each answer given up to ``grace_s`` to go out: a scanner learns to send its series
        again, not that the network failed. Returns the sessions told."""
        with self.live_lock:
            live = list(self.live.items())
        for connection, _ in live:
            connection.stop(Saturated("the server is stopping: send the series again once it is back, or to "
                                      "another"), self.retry_after_s)
        for _, outbox in live:
            outbox.drain(grace_s)
        return len(live)

    def handle_error(self, request: object, client_address: object) -> None:
        """A connection's unexpected failure, logged by its type and place only: socketserver's own
        prints the traceback (whose messages may quote what the client sent) and the client's address."""
        exc = sys.exc_info()[1]
        log.error("mrd connection failed", extra={"error_type": type(exc).__name__,
                                                  "error_at": service_logging.error_at(exc) if exc else None})


def build_server(settings: Settings, host: str, port: int, limits: ServerLimits) -> MrdServer:
    """The server with the models and the default localiser of ``settings``; :class:`SystemExit` (2)
    when no model or no localiser named ``default`` is installed, or one does not load."""
    try:
        registry = ModelRegistry.from_directory(settings.models_dir, settings.default_model, settings.onnx_threads)
        localisers = Localisers.from_directory(settings.localisers_dir, settings.onnx_threads)
    except UnusableModelFile as exc:
        print(f"svrnet-mrd: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    if not registry.estimators:
        print(f"svrnet-mrd: no model in {settings.models_dir}", file=sys.stderr)
        raise SystemExit(2)
    localiser = localisers.default()
    if localiser is None:
        found = f" (found: {', '.join(sorted(localisers.localisers))})" if localisers.localisers else ""
        print(f"svrnet-mrd: no 'default' localiser in {settings.localisers_dir}{found}; MRD images carry no "
              "brain mask", file=sys.stderr)
        raise SystemExit(2)
    stream_limits = StreamLimits.of(settings)
    factory = session_factory(registry, localiser, stream_limits)
    return MrdServer((host, port), factory, stream_limits, limits, settings.retry_after_s)


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="svrnet-mrd", description="SVRnet poses for MRD (ISMRMRD) image streams: "
                                 "Gadgetron's external language interface, Siemens FIRE.")
    ap.add_argument("--host", default=DEFAULT_HOST,
                    help=f"address to listen on (default {DEFAULT_HOST}: this machine only; MRD has no keys, so "
                         "another address, e.g. the scanner network's or 0.0.0.0, is given here on purpose, never "
                         "taken from SVRNET_HOST, which opens the HTTP API)")
    ap.add_argument("--port", type=port_number, default=DEFAULT_PORT, help=f"TCP port (default {DEFAULT_PORT})")
    ap.add_argument("--max-sessions", type=positive(int), help="connections at once (default: SVRNET_STREAM_MAX_SESSIONS)")
    ap.add_argument("--idle-s", type=positive(float),
                    help="seconds a connection may stay silent (default: SVRNET_STREAM_IDLE_S)")
    return ap


def port_number(text: str) -> int:
    """An argparse type: a TCP port, 0-65535 (0: one the system chooses).

    Example:
        >>> port_number("7000")
        7000
        >>> port_number("70000")
        Traceback (most recent call last):
        ...
        argparse.ArgumentTypeError: '70000': a port is a whole number from 0 to 65535
    """
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r}: a port is a whole number from 0 to 65535")
    return value


def positive(kind: type) -> Callable[[str], int | float]:
    """An argparse type: a finite number of ``kind`` over 0 (0, a negative number or NaN is a usage
    error, not a default in disguise or a server that drops every connection).

    Example:
        >>> positive(float)("2.5"), positive(int)("4")
        (2.5, 4)
    """
    def parse(text: str) -> int | float:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not math.isfinite(value) or value <= 0:
            raise argparse.ArgumentTypeError(f"{text!r}: a number over 0 is required")
        return value
    return parse


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    settings = load_settings("svrnet-mrd")
    service_logging.configure(settings.log_level)
    warn_unknown_variables("svrnet-mrd")
    limits = ServerLimits(settings.stream_max_sessions if args.max_sessions is None else args.max_sessions,
                          settings.stream_idle_s if args.idle_s is None else args.idle_s)
    if problem := listen_problem(args.host, args.port, "--host", "--port"):
        print(f"svrnet-mrd: {problem}", file=sys.stderr)
        return 2
    server = build_server(settings, args.host, args.port, limits)
    limit_blas_threads(settings.blas_threads)               # the process's, once it is sure to serve

    def stop(signum: int, frame: object) -> None:  # noqa: ARG001
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, stop)
    host, port = server.server_address[:2]
    log.info("svrnet-mrd listening on %s:%s", host, port)
    if host not in ("127.0.0.1", "localhost", "::1"):          # MRD has no API key: any peer may take its sessions
        log.warning("svrnet-mrd has no authentication: serving every host that reaches this address; keep it on a "
                    "scanner's own network or behind a tunnel")
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        log.info("svrnet-mrd stopping: %d open sessions told to send again", server.tell_stopping())
        server.server_close()
    return 0


def run() -> None:
    """Console entry point."""
    sys.exit(main())
