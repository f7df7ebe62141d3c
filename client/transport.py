"""The client's HTTP plumbing: headers, retries with backoff, errors as typed exceptions, downloads.

:class:`Transport` sends one request of the API v1 and returns a successful response or raises the
:class:`~client.errors.SVRnetError` subclass its status means; :class:`~client.SVRnetClient` builds the
API's calls on it. Only httpx and the standard library are used.

Example (a fake server that is busy once):
    >>> import httpx
    >>> answers = iter([httpx.Response(503, headers={"Retry-After": "0"}), httpx.Response(200, json={"ok": 1})])
    >>> t = Transport("http://svr", transport=httpx.MockTransport(lambda request: next(answers)))
    >>> t._send("GET", "/v1/health").json()
    {'ok': 1}
"""

from __future__ import annotations

import os
import random
import secrets
import ssl
import time
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Self, Union
from urllib.parse import urlsplit, urlunsplit

import httpx

from client.errors import ArgumentError, ConnectionFailed, error_from_response, parse_retry_after
from client.launch import installed_version
from client.multipart import CHUNK, MultipartBody, ProgressCallback

PathLike = Union[str, "os.PathLike[str]"]

DEFAULT_SERVER = "http://127.0.0.1:8000"
DEFAULT_TIMEOUT = httpx.Timeout(connect=5.0, read=300.0, write=300.0, pool=5.0)
MAX_RETRY_SLEEP_S = 30.0
SMALL_CALL_READ_S = 30.0
"""The read timeout of a call that sends nothing and reads a small answer (a status, the models, a
cancel), where a server that says nothing for this long is stuck, not busy: the client's timeout,
made for uploads and reconstructions on a CPU, would hold a scanner script for minutes."""
_NO_RETRY_TRANSPORT = (httpx.ReadTimeout, httpx.WriteTimeout, httpx.UnsupportedProtocol)

USER_AGENT = "svrnet-client" + (f"/{release}" if (release := installed_version()) else "")


def sleep(seconds: float) -> None:
    """``time.sleep``; a seam for tests."""
    time.sleep(seconds)


IDEMPOTENCY_HEADER = "Idempotency-Key"
"""Sent with a job's submission, the same key with every retry of it: the server answers a retry with
the job the first attempt made, so a lost answer costs no second job."""


def new_idempotency_key() -> str:
    """A submission's key (:data:`IDEMPOTENCY_HEADER`): 32 random URL-safe characters.

    Example:
        >>> len(new_idempotency_key()), new_idempotency_key() != new_idempotency_key()
        (32, True)
    """
    return secrets.token_urlsafe(24)


def server_address(server: str, schemes: tuple[str, ...] = ("http", "https")) -> str:
    """``server`` where it is a URL of one of ``schemes``; else :class:`ArgumentError` naming ``server``
    (``svrnet`` ends with the usage exit code), before any request: a URL without its scheme otherwise
    fails only at the first call, as a connection error.

    Example:
        >>> server_address("http://127.0.0.1:8000")
        'http://127.0.0.1:8000'
        >>> server_address("127.0.0.1:8000")
        Traceback (most recent call last):
        ...
        client.errors.ArgumentError: server: '127.0.0.1:8000': give the server's URL with its scheme, e.g. http://127.0.0.1:8000
    """
    try:
        scheme = urlsplit(server).scheme.lower()
    except ValueError as exc:
        raise ArgumentError(f"server: {server!r}: {exc}") from None
    if scheme not in schemes:
        raise ArgumentError(f"server: {server!r}: give the server's URL with its scheme, e.g. http://127.0.0.1:8000")
    return server


def clean_api_key(key: str | None) -> str | None:
    """``key`` without surrounding blanks (a key file's line end), None for an empty one;
    :class:`~client.errors.ArgumentError` for a key with a control, blank or non-ASCII character
    inside, which no HTTP header can carry (the message never shows the key).

    Example:
        >>> clean_api_key("s3cret\\n"), clean_api_key("  ")
        ('s3cret', None)
    """
    if key is None or not key.strip():
        return None
    key = key.strip()
    if not all("!" <= c <= "~" for c in key):
        raise ArgumentError("api_key: the API key (--api-key, SVRNET_API_KEY) holds a control, blank or non-ASCII "
                            "character; check it")
    return key


def shown_url(url: str) -> str:
    """``url`` without a user name or password, for messages.

    Example:
        >>> shown_url("http://user:hunter2@scanner-pc:8000/v1/predict")
        'http://scanner-pc:8000/v1/predict'
    """
    parts = urlsplit(url)
    if "@" not in parts.netloc:
        return url
    return urlunsplit(parts._replace(netloc=parts.netloc.rsplit("@", 1)[1]))


def trusted(verify: ssl.SSLContext | str | bool | None) -> ssl.SSLContext | bool:
    """What an HTTPS (or WSS) server's certificate is checked against: ``verify`` as given (an SSL
    context, False for no check, a CA bundle's path), else the bundle ``SVRNET_CA_BUNDLE`` names (a
    site's own CA, as hospital servers use), else httpx's default: certifi's bundle, or
    ``SSL_CERT_FILE`` / ``SSL_CERT_DIR`` where set (not the operating system's store).

    Example:
        >>> trusted(False), trusted(None) is True or isinstance(trusted(None), ssl.SSLContext)
        (False, True)
    """
    if verify is None:
        verify = os.environ.get("SVRNET_CA_BUNDLE") or True
    if isinstance(verify, (str, os.PathLike)):
        path = Path(verify).expanduser()
        if not path.is_file():
            raise ArgumentError(f"verify: the CA bundle {path} (SVRNET_CA_BUNDLE or verify=) is not a file")
        try:
            return ssl.create_default_context(cafile=str(path))
        except ssl.SSLError as exc:
            raise ArgumentError(f"verify: {path} holds no CA certificate in PEM form ({exc})") from None
    return verify


class Transport:
    """Requests to one server with the client's headers and retry policy (see :class:`~client.SVRnetClient`
    for the arguments)."""

    def __init__(self, base_url: str | None = None, api_key: str | None = None,
                 timeout: httpx.Timeout | float | None = DEFAULT_TIMEOUT, retries: int = 3,
                 transport: httpx.BaseTransport | None = None, *, http: httpx.Client | None = None,
                 backoff_s: float = 0.5, verify: ssl.SSLContext | str | bool | None = None) -> None:
        if retries < 0:
            raise ValueError("retries must be >= 0")
        base_url = server_address(base_url or os.environ.get("SVRNET_SERVER") or DEFAULT_SERVER)   # as the CLI reads it
        self.api_key = clean_api_key(api_key if api_key is not None else os.environ.get("SVRNET_API_KEY"))
        self.retries = retries
        self.backoff_s = backoff_s
        self.answered = False
        """Whether the server has answered this client at all (any status): a server to wait for."""
        self._owns_http = http is None
        self._http = http if http is not None else httpx.Client(base_url=base_url, timeout=timeout,
                                                                 transport=transport, verify=trusted(verify))
        self.base_url = str(self._http.base_url)

    # -- lifecycle -----------------------------------------------------------------------------

    def close(self) -> None:
        """Close the connection pool (not that of an ``http`` client passed in)."""
        if self._owns_http:
            self._http.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.base_url!r}, api_key={'***' if self.api_key else None})"

    # -- plumbing ------------------------------------------------------------------------------

    def _headers(self, extra: Mapping[str, str] | None = None) -> dict[str, str]:
        headers = {"User-Agent": USER_AGENT}
        if self.api_key:
            headers["Authorization"] = f"Bearer {self.api_key}"
        headers.update(extra or {})
        return headers

    def _sleep_for(self, attempt: int, retry_after: float | None) -> float:
        """The wait before retry ``attempt + 1``: the server's ``Retry-After`` (else the backoff's first
        sleep), doubled at each retry, and up to a quarter longer at random, so that clients refused
        together do not all come back together; at most :data:`MAX_RETRY_SLEEP_S`."""
        base = retry_after if retry_after is not None else self.backoff_s
        delay = base * 2 ** attempt * (1.0 + 0.25 * random.random())
        return min(max(delay, 0.0), MAX_RETRY_SLEEP_S)

    def _again(self, attempt: int, exc: httpx.TransportError, keyed: bool = False) -> bool:
        """Whether a safe request whose ``attempt`` failed with ``exc`` is sent again (after the
        backoff's sleep): not past the retries, nor after a timeout (the server may still be at work on
        it) unless a keyed submission's answer was lost to a read timeout."""
        if attempt >= self.retries or (isinstance(exc, _NO_RETRY_TRANSPORT)
                                       and not (keyed and isinstance(exc, httpx.ReadTimeout))):
            return False
        sleep(self._sleep_for(attempt, None))
        return True

    def _send(self, method: str, path: str, *, body: MultipartBody | None = None,
              progress: ProgressCallback | None = None, stream: bool = False,
              params: Mapping[str, str] | None = None, headers: Mapping[str, str] | None = None) -> httpx.Response:
        """Send with retries; returns a successful response (still open when ``stream``), or raises. A
        request with an :data:`IDEMPOTENCY_HEADER` is retried as a GET is (its server answers a retry
        with what the first made)."""
        keyed = IDEMPOTENCY_HEADER in (headers or {})
        idempotent = method in ("GET", "HEAD") or keyed
        for attempt in range(self.retries + 1):
            extra = dict(headers or {})
            content = None
            if body is not None:
                extra |= {"Content-Type": body.content_type, "Content-Length": str(body.total)}
                content = body.chunks(progress)
            try:
                request = self._http.build_request(method, path, content=content, headers=self._headers(extra),
                                                   params=params, timeout=self._timeout_for(body, stream))
                response = self._http.send(request, stream=True)
            except httpx.TransportError as exc:
                if idempotent and self._again(attempt, exc, keyed):     # a keyed answer lost to a timeout too
                    continue
                raise self._transport_error(method, path, exc) from exc
            except httpx.InvalidURL as exc:
                raise ConnectionFailed(f"{method} {path}: invalid URL: {exc}") from exc
            self.answered = self.answered or response.status_code not in (502, 504)     # not a proxy's
            busy = response.status_code in (429, 503, 507)            # 507: the server's disk, full for now
            if busy or (idempotent and response.status_code in (502, 504)):   # or a proxy lost the answer
                response.read()
                response.close()
                retry_after = parse_retry_after(response.headers.get("retry-after"))
                # An upload is sent again only when the server said when (its refusals come before
                # any job exists); a wait longer than the cap is the caller's decision, not ours.
                retryable = idempotent or retry_after is not None
                if attempt < self.retries and retryable and (retry_after or 0.0) <= MAX_RETRY_SLEEP_S:
                    sleep(self._sleep_for(attempt, retry_after))
                    continue
                error = error_from_response(response)
                error.attempts = attempt + 1
                raise error
            if not response.is_success:              # 4xx/5xx, and redirects (never followed)
                response.read()
                response.close()
                raise error_from_response(response)
            if not stream:
                try:
                    response.read()
                except httpx.TransportError as exc:     # the answer cut off: asked again where that is safe
                    if idempotent and self._again(attempt, exc):
                        continue
                    raise self._transport_error(method, path, exc) from exc
                finally:
                    response.close()
            return response
        raise AssertionError("unreachable")  # pragma: no cover

    def _timeout_for(self, body: MultipartBody | None, stream: bool) -> httpx.Timeout:
        """The client's timeout; for a small call (no body, a small answer) its read at most
        :data:`SMALL_CALL_READ_S`."""
        timeout = self._http.timeout
        if body is not None or stream or timeout.read is None or timeout.read <= SMALL_CALL_READ_S:
            return timeout
        return httpx.Timeout(connect=timeout.connect, read=SMALL_CALL_READ_S, write=timeout.write, pool=timeout.pool)

    def _url(self, path: str) -> str:
        return str(self._http.base_url).rstrip("/") + "/" + path.lstrip("/")

    def _transport_error(self, method: str, path: str, exc: Exception) -> ConnectionFailed:
        reason = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        if isinstance(exc, (httpx.ReadTimeout, httpx.WriteTimeout)) and method in ("POST", "PUT"):
            reason += (" (no answer within the client's timeout: a large request on a CPU server can take longer; "
                       "raise SVRNET_TIMEOUT, in seconds, for svrnet, or timeout= of SVRnetClient)")
        elif isinstance(exc, httpx.ReadTimeout):
            reason += " (the server accepted the connection and said nothing: it is stuck or overloaded)"
        elif isinstance(exc, httpx.ConnectError) and _caused_by(exc, ssl.SSLCertVerificationError):
            reason += (f" (the certificate of {shown_url(self.base_url)} is not one this client trusts: give your "
                       "site's CA bundle with SVRNET_CA_BUNDLE, or verify= of SVRnetClient; never switch to http://, "
                       "which sends the API key in the clear)")
        elif isinstance(exc, httpx.ConnectError) and not self.answered and _caused_by(exc, ssl.SSLError):
            reason += (f" (the server at {shown_url(self.base_url)} does not speak TLS: give its address with "
                       "http://, as `make serve` serves it)")
        elif isinstance(exc, httpx.ConnectError) and not self.answered and _caused_by(exc, ConnectionRefusedError):
            reason += (f" (no server answers at {shown_url(self.base_url)}: is it running, and at this address and "
                       "port? `make serve` starts one; --server or SVRNET_SERVER names another)")
        return ConnectionFailed(f"{method} {shown_url(self._url(path))}: {reason}", title="Connection failed")

    @staticmethod
    def _json(response: httpx.Response) -> Any:
        try:
            return response.json()
        except ValueError as exc:           # a proxy's login page, another service: not an SVRnet answer
            raise ConnectionFailed(f"the server answered {response.status_code} with a body that is not JSON: not "
                                   "an SVRnet server (a proxy's page, another service at that address?)",
                                   status=response.status_code,
                                   request_id=response.headers.get("x-request-id")) from exc

    def _download(self, path: str, out_path: PathLike, progress: ProgressCallback | None,
                  gunzip: bool = False) -> Path:
        """``GET path`` into ``out_path``, written under a temporary name and renamed when whole; a
        download cut off is started again (up to the client's retries), never left half-written.
        ``gunzip``: the file comes gzipped and is written decompressed (``progress`` counts the bytes
        received)."""
        out = Path(out_path).expanduser()            # as a shell would: the CLI's paths come expanded already
        tmp = out.with_name(f".{out.name}.part-{secrets.token_hex(4)}")
        for attempt in range(self.retries + 1):
            response = self._send("GET", path, stream=True)
            try:
                if response.headers.get("content-type", "").lower().startswith(("text/html", "text/plain")):
                    raise ConnectionFailed(f"GET {path}: the server answered {response.status_code} with a "
                                           f"{response.headers['content-type'].split(';')[0]} page, not the file: "
                                           "not an SVRnet server (a proxy's login page?); nothing was written",
                                           status=response.status_code)
                total = int(response.headers.get("content-length") or 0)
                done = 0
                inflate = zlib.decompressobj(wbits=31) if gunzip else None     # 31: a gzip member
                with open(tmp, "wb") as fh:
                    for data in response.iter_bytes(CHUNK):
                        try:
                            fh.write(data if inflate is None else inflate.decompress(data))
                        except zlib.error as exc:          # corrupt on the way: fetched again, as a cut-off one
                            raise httpx.ReadError(f"the gzipped file does not inflate ({exc})") from exc
                        done += len(data)
                        if progress is not None:
                            progress(done, total or done)
                    if inflate is not None and not inflate.eof:
                        raise httpx.ReadError("the gzipped file ended early")
                os.replace(tmp, out)
                return out
            except httpx.TransportError as exc:
                if self._again(attempt, exc):
                    continue
                raise self._transport_error("GET", path, exc) from exc
            finally:
                response.close()
                tmp.unlink(missing_ok=True)
        raise AssertionError("unreachable")  # pragma: no cover


def _caused_by(exc: BaseException, kind: type[BaseException]) -> bool:
    """Whether ``exc`` or an exception it was raised from or while handling is a ``kind``.

    Example:
        >>> try:
        ...     try:
        ...         raise ConnectionRefusedError(111, "refused")
        ...     except OSError as inner:
        ...         raise RuntimeError("connect failed") from inner
        ... except RuntimeError as outer:
        ...     _caused_by(outer, ConnectionRefusedError), _caused_by(outer, TimeoutError)
        (True, False)
    """
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, kind):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False
