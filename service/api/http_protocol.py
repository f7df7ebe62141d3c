"""uvicorn's HTTP/1.1 protocol with a deadline on every request's headers.

uvicorn closes a kept-alive connection that sends nothing, but it waits for ever on one that never
finishes its headers: a client trickling a header line every few seconds (or one that connects and
says nothing) holds a connection and a socket as long as it likes. Here each request's headers must
be whole within ``header_timeout_s`` of the connection opening or of the previous answer; otherwise the
connection is closed. The body's time is limited by :class:`service.api.middleware.RequestContext`
(408), which sees the request once its headers are in.

Example:
    >>> protocol = with_header_deadline(30.0)
    >>> protocol.header_timeout_s
    30.0
"""

from __future__ import annotations

import asyncio
import logging

from uvicorn.protocols.http.h11_impl import H11Protocol

log = logging.getLogger("service.access")


class HeaderDeadlineProtocol(H11Protocol):
    """:class:`H11Protocol` that closes a connection whose next request's headers do not arrive whole in
    time. It watches only what uvicorn exposes to every protocol: a new request cycle, the transport's
    protocol (replaced by a WebSocket upgrade) and the end of each answer."""

    header_timeout_s = 60.0

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        self._header_timer: asyncio.TimerHandle | None = None
        super().connection_made(transport)
        self._arm()

    def handle_events(self) -> None:
        cycle = self.cycle
        super().handle_events()
        if self.cycle is not cycle or self.transport.get_protocol() is not self:
            self._disarm()                   # a request's headers are in (or the connection is a WebSocket's)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm()                      # the next request's headers, if any, start their own clock

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def _arm(self) -> None:
        self._disarm()
        self._header_timer = self.loop.call_later(self.header_timeout_s, self._headers_too_slow)

    def _disarm(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _headers_too_slow(self) -> None:
        self._header_timer = None
        if not self.transport.is_closing():
            log.info("connection closed: request headers not whole in time")
            self.transport.close()


def with_header_deadline(header_timeout_s: float) -> type[HeaderDeadlineProtocol]:
    """The protocol class to pass to ``uvicorn.run(http=...)`` with this deadline."""
    return type("HeaderDeadlineProtocol", (HeaderDeadlineProtocol,), {"header_timeout_s": float(header_timeout_s)})
