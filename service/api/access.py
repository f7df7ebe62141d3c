"""Who may call the service: API keys, the browser origins it serves, and the key a job belongs to.

No key is stored anywhere: a key is compared in constant time where it is presented, and where the
server keeps who made something (a job's owner, the scope of its idempotency key) it keeps a digest
(:func:`key_owner`). The route dependencies that apply these rules are in :mod:`service.api.deps`.

Example:
    >>> api_key_ok(set(), None, None), api_key_ok({"k-1"}, "Bearer k-1", None), needs_key(Settings(), "/healthz")
    (True, True, False)
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
from urllib.parse import urlsplit

from starlette.datastructures import Headers

from service.core.settings import Settings, plain_origin


def api_key_ok(keys: set[str], authorization: str | None, x_api_key: str | None) -> bool:
    """``Authorization: Bearer <key>`` or ``X-API-Key: <key>`` is one of ``keys`` (always true without keys),
    compared in constant time. Keys are printable ASCII (the settings check them): a key sent with
    any other character is no key, whatever it holds.

    Example:
        >>> api_key_ok({"k-1"}, None, "k-1"), api_key_ok({"k-1"}, "Bearer café", None), api_key_ok({"k-1"}, None, "\\ud800")
        (True, False, False)
    """
    if not keys:
        return True
    given = presented_key(authorization, x_api_key)
    if not given or not given.isascii():
        return False
    return any(hmac.compare_digest(given.encode(), k.encode()) for k in keys)


def presented_key(authorization: str | None, x_api_key: str | None) -> str:
    """The API key a request presents (``Authorization: Bearer`` first, else ``X-API-Key``), or ``""``.

    Example:
        >>> presented_key("Bearer k-1 ", None), presented_key(None, "k-2"), presented_key("Basic x", None)
        ('k-1', 'k-2', '')
    """
    if authorization and authorization.lower().startswith("bearer "):
        return authorization[7:].strip()
    return x_api_key or ""


def origin_ok(settings: Settings, headers: dict[str, str]) -> bool:
    """Whether a request may come from where its ``Origin`` header says (lower-case ``headers``).

    Scripts and the client send no ``Origin``; browsers do, and a page the user merely visits can
    post a form to, or open a websocket on, a service on their machine without any CORS
    permission. Without API keys, a request carrying an ``Origin`` is therefore served only from the
    server's own pages at an address (an IP literal or ``localhost``, which a rebound DNS name
    cannot pose as) or from one of ``allowed_origins``; with keys, the key decides. A request
    without an ``Origin`` (a script's, or a page's same-origin ``GET``) is served where the server is
    reached at an address or at a listed origin (its ``Host``), so a page whose DNS name was rebound
    to the server cannot read it either: browsers do not send ``Sec-Fetch-Site`` to a plain-HTTP
    name, so a page's ``GET`` there looks like a script's. An address typed in a browser that says
    so (``Sec-Fetch-Site: none``, which no page can send) is served at any ``Host``.

    Example:
        >>> s = Settings(allowed_origins="https://viewer.example")
        >>> [origin_ok(s, {"host": "127.0.0.1:8000", "origin": o}) for o in
        ...  (None, "http://127.0.0.1:8000", "https://viewer.example", "https://evil.example", "null")]
        [True, True, True, False, False]
        >>> origin_ok(s, {"host": "evil.example:8000", "origin": "http://evil.example:8000"})
        False
        >>> [origin_ok(s, {"host": h, "sec-fetch-site": site}) for h, site in
        ...  (("evil.example:8000", "same-origin"), ("localhost:8000", "same-origin"), ("evil.example:8000", "none"),
        ...   ("viewer.example", "same-origin"))]
        [False, True, True, True]
        >>> [origin_ok(s, {"host": h}) for h in ("127.0.0.1:8000", "svr.example:8000", "viewer.example")]
        [True, False, True]
        >>> origin_ok(s, {})                          # no Host: no browser's request
        True
    """
    origin = headers.get("origin")
    if settings.key_set():
        return True
    allowed = settings.origin_set()
    if origin is None:
        host = headers.get("host")
        if host is None:                             # HTTP/1.0 without one: no browser sends that
            return True
        return (headers.get("sec-fetch-site") == "none" or _at_address(host) or "*" in allowed
                or any(plain_origin(f"{scheme}://{host}") in allowed for scheme in ("http", "https")))
    origin = plain_origin(origin)
    if "*" in allowed or origin in allowed:
        return True
    try:
        parts = urlsplit(origin)
    except ValueError:
        return False
    return (_at_address(parts.netloc) and parts.scheme in ("http", "https")
            and parts.netloc == headers.get("host", "").lower())


def _at_address(netloc: str) -> bool:
    """Whether ``host[:port]`` names an IP literal or ``localhost``, which no DNS name can pose as.

    Example:
        >>> [_at_address(h) for h in ("127.0.0.1:8000", "[::1]:8000", "localhost", "evil.example:8000", "")]
        [True, True, True, False, False]
    """
    try:
        host = urlsplit(f"//{netloc}").hostname or ""
        return host == "localhost" or bool(ipaddress.ip_address(host))
    except ValueError:
        return False


FOREIGN_ORIGIN = ("Origin: this server serves browser pages of its own address only; list the page's origin "
                  "in SVRNET_ALLOWED_ORIGINS, or configure API keys")
FOREIGN_HOST = ("Host: a server without API keys answers at an IP address or localhost (a web page whose DNS name "
                "was pointed at it could otherwise read it); list this address (http://NAME:PORT) in "
                "SVRNET_ALLOWED_ORIGINS, or configure API keys")

UNAUTHORIZED = "Authorization: a valid API key is required (Bearer token or X-API-Key header)"


def needs_key(settings: Settings, path: str) -> bool:
    """Whether ``path`` is protected by the API keys (when some are configured)."""
    return path.startswith("/v1/") or (path == "/metrics" and not settings.metrics_public)


def key_owner(api_key: str) -> str:
    """The digest that stands for the client presenting ``api_key`` wherever the server keeps who made
    something (a job's owner, the scope of its idempotency key): no key is stored.

    Example:
        >>> key_owner("k-1")[:16], key_owner("k-1") == key_owner("k-2")
        ('7c35c5a1785d2070', False)
    """
    return hashlib.sha256(api_key.encode("utf-8", "replace")).hexdigest()


def job_owner(settings: Settings, headers: Headers) -> str | None:
    """Who a request acts for where jobs are concerned: the digest of its API key (:func:`key_owner`)
    on a server with keys, None on one without (every client is then the same client)."""
    if not settings.key_set():
        return None
    return key_owner(presented_key(headers.get("authorization"), headers.get("x-api-key")))


CORS_HEADERS = ("Authorization", "X-API-Key", "Idempotency-Key", "Content-Type", "X-Request-ID")
"""What a listed origin's page may send across origins (:class:`ListedOriginsCors`)."""
CORS_EXPOSED = ("Location", "Retry-After", "X-Request-ID", "Content-Disposition")
"""What such a page may read of an answer besides its body."""


class ListedOriginsCors:
    """The CORS answers browsers need before a page of another origin may read the service's answers,
    for the origins ``SVRNET_ALLOWED_ORIGINS`` lists alone, with or without API keys (Starlette's
    ``CORSMiddleware``, preflights answered before the key check: a browser sends no key with one).
    A request from any other origin goes on to the service's own rules (:func:`origin_ok` without
    keys, the key with them) and gets no CORS header: its page cannot read the answer.

    Example:
        >>> import asyncio
        >>> async def app(scope, receive, send): pass
        >>> cors = ListedOriginsCors(app, {"https://viewer.example"})
        >>> sent = []
        >>> async def send(message): sent.append(message)
        >>> scope = {"type": "http", "method": "OPTIONS", "path": "/v1/predict", "headers": [
        ...     (b"origin", b"https://viewer.example"), (b"access-control-request-method", b"POST")]}
        >>> asyncio.run(cors(scope, None, send))
        >>> sent[0]["status"], dict(sent[0]["headers"])[b"access-control-allow-origin"]
        (200, b'https://viewer.example')
    """

    def __init__(self, app, origins: set[str]) -> None:  # noqa: ANN001 - an ASGI app
        from starlette.middleware.cors import CORSMiddleware

        self.app, self.origins = app, frozenset(origins)
        self.cors = CORSMiddleware(app, allow_origins=["*"] if "*" in origins else sorted(origins),
                                   allow_methods=["GET", "POST", "DELETE"], allow_headers=list(CORS_HEADERS),
                                   expose_headers=list(CORS_EXPOSED), max_age=600)

    async def __call__(self, scope, receive, send) -> None:  # noqa: ANN001 - ASGI
        if scope["type"] == "http":
            origin = Headers(scope=scope).get("origin")
            if origin is not None and ("*" in self.origins or plain_origin(origin) in self.origins):
                await self.cors(scope, receive, send)
                return
        await self.app(scope, receive, send)
