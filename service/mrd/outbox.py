"""An MRD connection's answers, written to the client by a thread of their own.

A scanner-side client may send a whole series before it reads anything (a script that writes every
image, then reads the answers). Written from the thread that reads the images, the answers (each
image comes back whole, with its pose) fill the socket's buffers after some megabytes; the server
then stops reading, the client stops sending, and both wait until the idle limit ends the session
with nothing delivered. :class:`Outbox` queues each answer instead and a writer thread sends it, so
the server goes on reading while the client is not reading yet. What it holds unsent is bounded (by
the session's memory limit, ``SVRNET_STREAM_MAX_SESSION_MB``: the answers are about as large as the
slices they answer): past that, the answering thread waits for the client to read, and a client
that reads nothing for the idle limit loses the connection (:class:`TimeoutError`).

Example (a client that reads only after it has sent everything):
    >>> import socket
    >>> server_end, client_end = socket.socketpair()
    >>> box = Outbox(server_end, idle_s=5.0)
    >>> for k in range(3):
    ...     _ = box.write(b"answer %d;" % k); box.flush()
    >>> box.drain(5.0)
    True
    >>> client_end.recv(100)
    b'answer 0;answer 1;answer 2;'
"""

from __future__ import annotations

import socket
import threading
import time
from collections import deque

MAX_UNREAD_BYTES = 256 << 20
"""What one connection holds unsent at most, by default (a stream session's own memory limit)."""


POLL_S = 5.0
"""How often a writer blocked by a client that does not read checks whether the client is still
active (sending): an active client is waited for, one silent for the idle limit is not."""


class Outbox:
    """A file-like sink (``write``, ``flush``) whose flushed messages a thread sends, in order, on a
    duplicate of ``sock``; :meth:`drain` waits for them. A send blocks for as long as the client
    goes on sending (each :meth:`flush` answers a message of it) and at most ``idle_s`` after that."""

    def __init__(self, sock: socket.socket, idle_s: float, max_unread_bytes: int = MAX_UNREAD_BYTES) -> None:
        self.sock = sock.dup()                       # its own timeout: the reader's changes per message
        self.sock.settimeout(min(POLL_S, idle_s))
        self.idle_s, self.max_unread_bytes = idle_s, max_unread_bytes
        self.active_at = self.progress_at = time.monotonic()
        self.current = bytearray()
        self.queue: deque[bytearray] = deque()
        self.unsent = 0
        self.sending = False
        self.failure: OSError | None = None
        self.closing = False
        self.changed = threading.Condition()
        self.thread = threading.Thread(target=self._send_all, name="svrnet-mrd-outbox", daemon=True)
        self.thread.start()

    # -- the answering side ----------------------------------------------------------------------------------
    def write(self, data: bytes) -> int:
        """Add ``data`` (bytes, or a ctypes header as ismrmrd writes them) to the message being written."""
        view = memoryview(data).cast("B")
        self.current += view
        return view.nbytes

    def flush(self) -> None:
        """Queue what was written since the last flush as one message; wait while
        ``max_unread_bytes`` are unsent, at most ``idle_s``.

        Raises:
            TimeoutError: the client has read none of its answers for ``idle_s`` (from now on every
                flush raises at once).
            ConnectionError: the client is gone; nothing more goes out.
        """
        message, self.current = self.current, bytearray()
        with self.changed:
            self.active_at = time.monotonic()
            deadline = self.active_at + self.idle_s
            while self.failure is None and self.unsent and self.unsent + len(message) > self.max_unread_bytes:
                if not self.changed.wait(deadline - time.monotonic()):
                    self._fail(TimeoutError())
            if isinstance(self.failure, TimeoutError):
                raise TimeoutError(f"the client read none of its answers for {self.idle_s:g} s")
            if self.failure is not None:
                raise ConnectionError(f"the answers could not be sent ({type(self.failure).__name__})")
            if message:
                self.queue.append(message)
                self.unsent += len(message)
                self.changed.notify_all()

    def drain(self, timeout_s: float) -> bool:
        """Wait until every queued message is sent, for as long as the client reads some of them
        every ``timeout_s``; then stop the writer and close the duplicate socket. Safe to call again.

        Returns:
            True when everything was sent; False when the client is gone or stopped reading.
        """
        called = time.monotonic()
        with self.changed:
            while self.failure is None and (self.queue or self.sending):
                deadline = max(self.progress_at, called) + timeout_s
                if not self.changed.wait(max(deadline - time.monotonic(), 0.0)) and time.monotonic() >= deadline:
                    self._fail(TimeoutError())
            done = self.failure is None
            self.closing = True
            self.changed.notify_all()
        self.thread.join(timeout=POLL_S + 1.0)     # a send in progress gives up at its next poll
        self.sock.close()
        return done

    # -- the writer thread -----------------------------------------------------------------------------------
    def _fail(self, failure: OSError) -> None:
        """Under the lock: nothing more goes out; every waiter learns it."""
        if self.failure is None:
            self.failure = failure
        self.queue.clear()
        self.unsent = 0
        self.changed.notify_all()

    def _send_all(self) -> None:
        """The writer thread: the queued messages, in order, until :meth:`drain` or a failure."""
        while True:
            with self.changed:
                while not self.queue and not self.closing and self.failure is None:
                    self.changed.wait()
                if not self.queue or self.failure is not None:
                    return
                message = self.queue.popleft()
                self.sending = True
            try:
                self._send(message)
            except OSError as failure:               # gone, or not reading: nothing more goes out
                with self.changed:
                    self.sending = False
                    self._fail(failure)
                return
            with self.changed:
                self.sending = False
                self.unsent -= len(message)
                self.changed.notify_all()

    def _send(self, message: bytearray) -> None:
        """Send ``message`` whole, waiting for the client to read while it is active and the outbox
        has not failed (a drain that gave up, a flush that timed out)."""
        view = memoryview(message)
        while view.nbytes:
            try:
                view = view[self.sock.send(view):]
                self.progress_at = time.monotonic()
            except TimeoutError:
                if self.failure is not None or time.monotonic() - self.active_at >= self.idle_s:
                    raise
