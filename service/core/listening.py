"""Whether a server can listen where its settings say, asked before it loads anything.

uvicorn binds its socket after the application has started (models loaded, the job runner up) and
reports a bad address as ``[Errno -2] Name or service not known``, naming neither the setting nor
the address. :func:`listen_problem` resolves and binds the address first, so that ``svrnet-server``
and ``svrnet-mrd`` stop in one line naming the variable to change.

Example:
    >>> listen_problem("127.0.0.1", 0) is None, listen_problem("localhost", 0) is None
    (True, True)
    >>> listen_problem("192.0.2.1", 8000).startswith("SVRNET_HOST: cannot listen on '192.0.2.1'")   # no machine's
    True
    >>> listen_problem("no-such-host.invalid", 8000).startswith("SVRNET_HOST: cannot listen on 'no-such-host.invalid'")
    True
"""

from __future__ import annotations

import errno
import socket


def listen_problem(host: str, port: int, host_setting: str = "SVRNET_HOST", port_setting: str = "SVRNET_PORT",
                   ) -> str | None:
    """What keeps a server from listening on ``host:port``, naming the setting to change (``host_setting``
    or ``port_setting``), or None. Every address ``host`` resolves to is bound and let go at once
    (``SO_REUSEADDR``, as uvicorn and socketserver set it); as asyncio's server does, an address of a
    family the machine has not enabled (``localhost`` as ``::1`` without IPv6) is passed over where
    another binds."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as exc:
        reason = exc.strerror if isinstance(exc, socket.gaierror) else "not a host name"
        return f"{host_setting}: cannot listen on {host!r} ({reason}): give an address of this machine (0.0.0.0: all)"
    bound, unavailable = 0, "no address"
    for family, kind, proto, _, address in infos:
        try:
            with socket.socket(family, kind, proto) as probe:
                probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                probe.bind(address)
                bound += 1
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                return f"{port_setting}: port {port} on {host} is in use by another program"
            unavailable = exc.strerror or str(exc)
    if not bound:
        return f"{host_setting}: cannot listen on {host!r} ({unavailable}): give an address of this machine"
    return None
