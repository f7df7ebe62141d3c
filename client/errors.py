"""Typed exceptions of the SVRnet client, one per failure kind of the HTTP API v1.

Every error the server answers is an RFC 7807 ``application/problem+json`` body
(``{"type", "title", "status", "detail"}`` plus ``request_id``); :func:`error_from_response`
turns such a response into the matching subclass of :class:`SVRnetError`, keeping those fields.

Example:
    >>> from client import SVRnetClient, UnusableInput
    >>> try:                                                       # doctest: +SKIP
    ...     SVRnetClient().predict(["flat.nii.gz"])
    ... except UnusableInput as e:
    ...     print(e.status, e.detail)
    422 stacks: flat.nii.gz is a 2D image
"""

from __future__ import annotations

import json
from typing import Any

import httpx

__all__ = [
    "SVRnetError", "BadRequest", "Unauthorized", "OriginNotAllowed", "NotFound", "Conflict", "KeyReused",
    "PayloadTooLarge", "UnsupportedFile", "UnusableInput", "Busy", "ServerError", "ConnectionFailed", "JobFailed",
    "WaitTimeout",
    "error_from_response", "error_class_for_status", "ArgumentError",
]


class ArgumentError(ValueError):
    """Arguments the client itself refuses before sending anything (masks that do not match the
    stacks, a folder without files, an acquisition order that does not fit a stack): ``svrnet`` ends
    with the usage exit code (2), naming the argument."""


class SVRnetError(Exception):
    """Base class of every client error.

    Attributes:
        status: the HTTP status (``None`` when no response came back).
        title: the problem title, or the reason phrase.
        detail: the problem detail: names the offending field or file.
        request_id: the server's request id (quote it in bug reports), when known.
        type: the problem type URI, when given.
        body: the decoded problem body (empty when the body was not JSON).
        attempts: how many times the request was sent before this answer (1: not retried).
        idempotency_key: a job submission's key (None for other requests): sent again with it, the
            submission gets the job the first one made, if any.
    """

    def __init__(self, detail: str, *, status: int | None = None, title: str | None = None,
                 request_id: str | None = None, type: str | None = None,  # noqa: A002 - RFC 7807 field name
                 body: dict[str, Any] | None = None) -> None:
        super().__init__(detail)
        self.status = status
        self.title = title
        self.detail = detail
        self.request_id = request_id
        self.type = type
        self.attempts = 1
        self.idempotency_key: str | None = None
        self.body = body or {}

    def __str__(self) -> str:
        head = " ".join(str(p) for p in (self.status, self.title) if p)
        text = f"{head}: {self.detail}" if head else self.detail
        return f"{text} (request id {self.request_id})" if self.request_id else text


class BadRequest(SVRnetError):
    """400 (and any other 4xx without a class of its own): the request itself is malformed -- a missing
    field, a parameter out of range, more masks than stacks, a ``poses`` body that does not fit."""


class Unauthorized(SVRnetError):
    """401/403: missing or wrong API key (set ``SVRNET_API_KEY`` or pass ``api_key=``).

    Attributes:
        key_sent: whether the refused request carried a key (None: not known).
    """

    def __init__(self, detail: str, *, key_sent: bool | None = None, **kwargs: Any) -> None:
        super().__init__(detail, **kwargs)
        self.key_sent = key_sent


class OriginNotAllowed(Unauthorized):
    """403 ``/problems/origin-not-allowed``: the request carried a browser's ``Origin`` of another site
    than the server's own or its ``SVRNET_ALLOWED_ORIGINS``; the API key is not the problem."""


class NotFound(SVRnetError):
    """404: unknown model or job."""


class Conflict(SVRnetError):
    """409: e.g. a reconstruction result asked for before the job succeeded."""


class KeyReused(Conflict):
    """422 ``/problems/idempotency-key-reused``: the ``Idempotency-Key`` made a job from another
    request (other files, poses or options); send this request under a new key. The files are not at
    fault, so this is no :class:`UnusableInput`."""


class PayloadTooLarge(SVRnetError):
    """413: the upload is over the server's limit."""


class UnsupportedFile(SVRnetError):
    """415: a file that cannot be read at all (not an image, unknown format, truncated)."""


class UnusableInput(SVRnetError):
    """422: a readable file that cannot be used (2D, 4D, NaN, mask grid differs from its stack ...)."""


class Busy(SVRnetError):
    """429/503 (or 507: the server's disk is full for now) still answered after every retry.

    Attributes:
        retry_after_s: the server's last ``Retry-After`` in seconds, when it sent one.
    """

    def __init__(self, detail: str, *, retry_after_s: float | None = None, **kwargs: Any) -> None:
        super().__init__(detail, **kwargs)
        self.retry_after_s = retry_after_s


class ServerError(SVRnetError):
    """5xx other than 503: a fault on the server side; quote :attr:`request_id`."""


class ConnectionFailed(SVRnetError):
    """No HTTP answer (connection refused, DNS failure, timeout, connection dropped), or a 408: the
    upload did not reach the server in time."""


class JobFailed(SVRnetError):
    """A reconstruction job ended ``failed`` or ``cancelled``.

    Attributes:
        job_id: the job.
        job_status: ``"failed"`` or ``"cancelled"``.
        job: the last ``GET /v1/reconstructions/{job_id}`` body.
    """

    def __init__(self, job: dict[str, Any]) -> None:
        self.job = job
        self.job_id = str(job.get("job_id", ""))
        self.job_status = str(job.get("status", ""))
        error = job.get("error")
        reason = f": {error}" if error else ""
        super().__init__(f"job {self.job_id} {self.job_status}{reason}", title=f"Job {self.job_status}")


class WaitTimeout(SVRnetError):
    """:meth:`SVRnetClient.wait` gave up before the job finished (the job itself goes on)."""

    def __init__(self, detail: str, *, job: dict[str, Any] | None = None) -> None:
        super().__init__(detail, title="Timed out waiting")
        self.job = job or {}


_BY_STATUS: dict[int, type[SVRnetError]] = {
    400: BadRequest, 401: Unauthorized, 403: Unauthorized, 404: NotFound, 408: ConnectionFailed, 409: Conflict,
    413: PayloadTooLarge, 415: UnsupportedFile, 422: UnusableInput, 429: Busy, 503: Busy, 507: Busy,
}
"""408 (the upload did not arrive in time) is the connection's fault, not the files'; 507 (the
server's disk filled, ``Retry-After`` given) is a busy server's, retried as a 503 is."""


_BY_TYPE: dict[tuple[int, str], type[SVRnetError]] = {
    (422, "/problems/idempotency-key-reused"): KeyReused, (403, "/problems/origin-not-allowed"): OriginNotAllowed,
}
"""Problem types whose status another kind of failure shares (422 unusable images, 403 refused keys)."""


def error_class_for_status(status: int, problem_type: str | None = None) -> type[SVRnetError]:
    """The exception class for an HTTP error status, and the problem ``type`` where it says more.

    Example:
        >>> error_class_for_status(422).__name__
        'UnusableInput'
        >>> error_class_for_status(422, "/problems/idempotency-key-reused").__name__
        'KeyReused'
        >>> [error_class_for_status(s).__name__ for s in (502, 408, 507)]
        ['ServerError', 'ConnectionFailed', 'Busy']
    """
    if isinstance(problem_type, str) and (status, problem_type) in _BY_TYPE:
        return _BY_TYPE[status, problem_type]
    if status in _BY_STATUS:
        return _BY_STATUS[status]
    if 400 <= status < 500:
        return BadRequest
    if status >= 500:
        return ServerError
    return SVRnetError


def parse_retry_after(value: str | None) -> float | None:
    """``Retry-After`` in seconds (delta-seconds or an HTTP date), ``None`` when absent or unreadable."""
    if not value:
        return None
    value = value.strip()
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    from datetime import datetime, timezone
    from email.utils import parsedate_to_datetime

    try:
        when = parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    if when.tzinfo is None:
        when = when.replace(tzinfo=timezone.utc)
    return max(0.0, (when - datetime.now(timezone.utc)).total_seconds())


def _content_kind(response: httpx.Response) -> str:
    """What an answer's body is, in a few words (never its text)."""
    kind = response.headers.get("content-type", "").split(";")[0].strip()
    return kind or "no content type"


NOT_SVRNET = (404, 405, 501)
"""Statuses that, without a problem+json body, say the address is another server (SVRnet answers a
404 or 405 as problem+json and never 501 Not Implemented, a plain web server's answer to a POST)."""


def error_from_response(response: httpx.Response) -> SVRnetError:
    """The typed exception for an error ``response`` (its body must have been read).

    Reads the problem+json fields when the body is JSON; otherwise the detail is the start of the
    body text. The request id comes from the body or the ``X-Request-ID`` header.

    Example:
        >>> r = httpx.Response(404, json={"type": "/problems/not-found", "title": "Not found",
        ...                               "status": 404, "detail": "model: unknown model 'x'"})
        >>> e = error_from_response(r)
        >>> type(e).__name__, e.detail
        ('NotFound', "model: unknown model 'x'")
        >>> type(error_from_response(httpx.Response(501, text="<html>Unsupported method</html>"))).__name__
        'ConnectionFailed'
    """
    status = response.status_code
    body: dict[str, Any] = {}
    try:
        decoded = json.loads(response.content) if response.content else None
        if isinstance(decoded, dict):
            body = decoded
    except (ValueError, UnicodeDecodeError):
        pass
    title = body.get("title") or response.reason_phrase or None
    detail = body.get("detail")
    if not isinstance(detail, str) or not detail:
        detail = str(detail) if detail else (response.text.strip()[:300] if response.content and not body else "")
        detail = detail or (title or f"HTTP {status}")
    if 300 <= status < 400:                   # the client follows no redirect: most likely a wrong URL
        detail = (f"the server answered a redirect ({status}) to {response.headers.get('location', '?')}; "
                  "check the server URL")
    elif status in NOT_SVRNET and "status" not in body:      # every SVRnet 404 and 405 is problem+json
        detail = (f"the server answered {status} without a problem+json body ({_content_kind(response)}): it is "
                  "not an SVRnet API v1 server; check the server URL and port")
    request_id = body.get("request_id") or response.headers.get("x-request-id")
    kwargs: dict[str, Any] = {"status": status, "title": str(title) if title else None,
                              "request_id": request_id, "type": body.get("type"), "body": body}
    if 300 <= status < 400 or (status in NOT_SVRNET and "status" not in body):
        return ConnectionFailed(detail, **kwargs)     # the wrong server: as one that cannot be reached
    if status == 404 and detail.startswith("no route "):
        return ConnectionFailed(detail, **kwargs)     # the right server at the wrong URL: check the server URL
    cls = error_class_for_status(status, body.get("type"))
    if cls is Busy:
        return Busy(detail, retry_after_s=parse_retry_after(response.headers.get("retry-after")), **kwargs)
    if issubclass(cls, Unauthorized):
        return cls(detail, key_sent=_key_sent(response), **kwargs)
    return cls(detail, **kwargs)


def _key_sent(response: httpx.Response) -> bool | None:
    """Whether the request ``response`` answers carried an API key (None: the request is not known)."""
    try:
        headers = response.request.headers
    except RuntimeError:                       # a response made without its request
        return None
    return "authorization" in headers or "x-api-key" in headers
