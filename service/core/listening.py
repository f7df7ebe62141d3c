"""Whether a server can listen where its settings say, asked before it loads anything.

uvicorn binds its socket after the application has started (models loaded, the job runner up) and
reports a bad address as ``[Errno -2] Name or service not known``, naming neither the setting nor
the address. :func:`listen_problem` resolves and binds the address first, so that ``svrnet-server``
and ``svrnet-mrd`` stop in one line naming the variable to change.

Example:
    >>> listen_problem("127.0.0.1", 0) is None
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
    or ``port_setting``), or None. The address is bound and let go at once (``SO_REUSEADDR``, as
    uvicorn and socketserver set it)."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                                             flags=socket.AI_PASSIVE)[0]
    except (socket.gaierror, UnicodeError) as exc:
        reason = exc.strerror if isinstance(exc, socket.gaierror) else "not a host name"
        return f"{host_setting}: cannot listen on {host!r} ({reason}): give an address of this machine (0.0.0.0: all)"
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(address)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                return f"{port_setting}: port {port} on {host} is in use by another program"
            return f"{host_setting}: cannot listen on {host!r} ({exc.strerror}): give an address of this machine"
    return None
