"""ASGI middleware: request ids, early refusals, the upload size and time limits, metrics and access logs."""

from __future__ import annotations

import asyncio
import functools
import json
import logging
import re
import time
import uuid
import weakref

from anyio import to_thread
from python_multipart.multipart import parse_options_header
from starlette.routing import compile_path
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.deps import PROCESSING_ROUTES, early_rejection, take_admission
from service.api.metrics import Metrics
from service.api.problems import MEDIA_TYPE, problem_body
from service.core.errors import (InternalError, MalformedRequest, NotReady, PayloadTooLarge, RequestTimeout, ServiceError,
                                 UnsupportedFile)
from service.core.logging import error_at

log = logging.getLogger("service.access")
SAFE_ID = re.compile(r"^[A-Za-z0-9._-]{1,64}$")
METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})
"""HTTP methods named in metrics and logs; any other token a client sends is ``other`` (a label
value per invented method would grow the metrics without bound)."""

FRAMING_AND_SNIFFING = ((b"x-frame-options", b"DENY"), (b"content-security-policy", b"frame-ancestors 'none'"),
                        (b"x-content-type-options", b"nosniff"))
"""Headers of every answer. No page of another site may frame this server's (the OpenAPI page's
requests are its own origin's, which a server without keys serves: framed, a click on the other
site's page could send them), and no answer is read as another type than it says (a problem+json
quotes the path it was asked for)."""


_TEMPLATES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def closing_delimiter(content_type: str) -> bytes | None:
    """The delimiter a multipart body ends with (``--BOUNDARY--``, RFC 2046), or None for another body
    (or one without a boundary, which the form parser refuses). The boundary is read as the form
    parser reads it (python-multipart's ``parse_options_header``: blanks around ``=``, quoting,
    other parameters before it), so that the check and the parser agree on every header.

    Example:
        >>> closing_delimiter('multipart/form-data; boundary="zz"'), closing_delimiter("application/json")
        (b'--zz--', None)
        >>> closing_delimiter("multipart/form-data; x-boundary=yy; boundary = zz ; charset=utf-8")
        b'--zz--'
    """
    if not content_type.lower().lstrip().startswith("multipart/"):
        return None
    boundary = parse_options_header(content_type)[1].get(b"boundary")
    return b"--" + boundary + b"--" if boundary else None


def first_values(scope: Scope) -> dict[str, str]:
    """A request's headers by lower-case name, each with its first value: the one the routes'
    dependencies and the form parser read (Starlette's ``Request.headers[name]``), so that the early
    refusals and the body's checks judge a header sent twice (an API key, an ``Origin``, the
    ``Content-Type`` and its boundary) as the route would, not by another copy.

    Example:
        >>> first_values({"headers": [(b"X-API-Key", b"k-1"), (b"x-api-key", b"k-2")]})
        {'x-api-key': 'k-1'}
    """
    headers: dict[str, str] = {}
    for k, v in scope.get("headers", []):
        headers.setdefault(k.decode("latin-1").lower(), v.decode("latin-1"))
    return headers


EPILOGUE_BYTES = 8 * 1024
"""What a multipart body may carry after its closing delimiter (RFC 2046's epilogue, which clients
leave empty or a line break) for the delimiter still to be found at its end."""
HEAD_BYTES = 1024
"""The first bytes of a multipart body kept to check where its first part begins."""


def cut_off(tail: bytes, delimiter: bytes) -> bool:
    """Whether a multipart body whose last bytes are ``tail`` stops before its closing delimiter: the
    form parser keeps the parts it finished and drops the one cut off, so the request would be
    answered for less than the client sent. (A part's own bytes never hold the delimiter: the
    boundary is chosen so.)

    Example:
        >>> cut_off(b"...data\\r\\n--zz--\\r\\n", b"--zz--"), cut_off(b"...half a file", b"--zz--")
        (False, True)
    """
    return delimiter not in tail


def form_problem(head: bytes, tail: bytes, delimiter: bytes) -> MalformedRequest | None:
    """Why a whole multipart body (its first bytes ``head``, its last ``tail``) cannot be read as the
    form its ``Content-Type`` announces (closing ``delimiter``), or None: its parts separated by
    another boundary, text before its first part (a preamble, which the form parser does not read),
    or a body that stops before its closing delimiter (:func:`cut_off`).

    Example:
        >>> for head in (b"--yy", b"note --zz", b"--zz x"):
        ...     print(form_problem(head, b"x", b"--zz--").detail[:46])
        the multipart body's parts are not separated b
        the multipart body starts with text before its
        the multipart body ends before its closing bou
        >>> form_problem(b"\\r\\n--zz x", b"x\\r\\n--zz--\\r\\n", b"--zz--") is None
        True
    """
    opening = delimiter[:-2]
    if not head.lstrip(b"\r\n").startswith(opening):
        if opening not in head:
            return MalformedRequest("the multipart body's parts are not separated by the boundary its Content-Type "
                                    "names: no part of it is used")
        return MalformedRequest("the multipart body starts with text before its first boundary (a preamble), "
                                "which is not read: start the body with its first part")
    if cut_off(tail, delimiter):
        return MalformedRequest("the multipart body ends before its closing boundary: it was cut off on the way, "
                                "and no part of it is used; send the request again")
    return None


def _templates(app: object) -> tuple[tuple[re.Pattern, str], ...]:
    """The app's documented path templates (its OpenAPI schema), each with its compiled pattern; made
    once per app, and gone with it."""
    openapi = getattr(app, "openapi", None)
    if openapi is None:                                 # a bare ASGI app (or none): nothing documented
        return ()
    if app not in _TEMPLATES:
        _TEMPLATES[app] = tuple((compile_path(t)[0], t) for t in openapi().get("paths", {}))
    return _TEMPLATES[app]


def route_of(app: object, scope: Scope) -> str:
    """The route template a request's path matches (``/v1/reconstructions/{job_id}``), for answers
    given before routing (a refused key, a busy server, a body too large); ``unmatched`` when none.
    The templates are the app's documented paths, compiled once per app.

    Example:
        >>> from fastapi import FastAPI
        >>> app = FastAPI()
        >>> _ = app.get("/v1/jobs/{job_id}")(lambda job_id: None)
        >>> route_of(app, {"path": "/v1/jobs/abc"}), route_of(app, {"path": "/x"})
        ('/v1/jobs/{job_id}', 'unmatched')
    """
    return next((t for pattern, t in _templates(app) if pattern.match(scope["path"])), "unmatched")


CLIENT_CLOSED = 499
"""The status recorded (log, metrics) for a request whose client went away before its body was whole
(nginx's convention): not the 400 the form parser makes of the cut-off body, which no client saw."""


class RequestContext:
    """The outermost layer of the app, around every request:

    * assigns ``X-Request-ID`` (kept from the client when it is a safe token) to every answer, with
      :data:`FRAMING_AND_SNIFFING`;
    * refuses what needs no body -- a missing API key, a full job queue -- before the upload is read
      (:func:`service.api.deps.early_rejection`), and admits a request to a processing route then too
      (:func:`service.api.deps.take_admission`: 503 at once when every admission is taken), held until
      the request ends (its processing slot is taken in the route's body, :func:`service.api.deps.processing`);
    * limits the body size: 413 from ``Content-Length`` at once, or as soon as a chunked body passes
      the limit, whatever the form parser makes of the cut-off body;
    * limits the body's time: 408 (and the connection closed) when no data comes for ``idle_s`` or the
      body is not whole ``timeout_s`` after the request began, so a client trickling bytes holds no
      connection for ever (the answer, once the body is in, has no such limit);
    * turns any unexpected exception into a 500 problem+json with the request id, logged by type
      only (no traceback reaches the client or the log, no patient data the log), and a request the
      server stops past its shutdown grace into a 503 (:data:`STOPPING`), counted and logged;
    * records metrics and writes one access-log line (:data:`CLIENT_CLOSED` for a client that left
      during its upload).
    """

    def __init__(self, app: ASGIApp, metrics: Metrics, max_body_bytes: int, idle_s: float = 60.0,
                 timeout_s: float = 900.0) -> None:
        self.app, self.metrics, self.max_body = app, metrics, max_body_bytes
        self.idle_s, self.timeout_s = idle_s, timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = first_values(scope)
        sent_method = scope["method"]
        if sent_method == "HEAD":                    # answered as GET, without the body (RFC 9110, 9.3.2)
            scope = {**scope, "method": "GET"}
        rid = headers.get("x-request-id", "")
        rid = rid if SAFE_ID.match(rid) else uuid.uuid4().hex
        scope.setdefault("state", {})["request_id"] = rid
        scope["state"]["sent_method"] = sent_method           # a download answers HEAD without reading its file
        start = time.perf_counter()
        state: dict = {"code": 500, "started": False, "received": 0, "refusal": None, "replaced": False,
                       "body_done": False, "left": False}
        body_deadline = asyncio.get_running_loop().time() + self.timeout_s
        delimiter = closing_delimiter(headers.get("content-type", ""))
        head, tail = b"", b""

        async def emit(message: Message) -> None:
            if message["type"] == "http.response.start":
                state["code"], state["started"] = message["status"], True
                message["headers"] = list(message.get("headers", [])) + [(b"x-request-id", rid.encode()),
                                                                         *FRAMING_AND_SNIFFING]
            elif sent_method == "HEAD" and message["type"] == "http.response.body":
                if message.get("more_body", False):
                    return
                message = {**message, "body": b""}
            await send(message)

        async def send_with_id(message: Message) -> None:
            if message["type"] == "http.response.start" and state["refusal"] and not state["started"]:
                # The body was cut off at a limit: whatever the app answers (the form parser
                # reports a 400), the client is told why (413, 408).
                state["replaced"] = True
                await self._problem(emit, rid, state["refusal"], close=not state["body_done"])
                return
            if state["replaced"]:
                return  # the body of the app's own answer, replaced above
            await emit(message)

        async def limited_receive() -> Message:
            nonlocal head, tail
            if state["body_done"]:                   # later calls wait for a disconnect: no limit
                return await receive()
            wait = min(self.idle_s, body_deadline - asyncio.get_running_loop().time())
            try:
                message = await asyncio.wait_for(receive(), timeout=max(wait, 0.0))
            except asyncio.TimeoutError:
                state["refusal"] = self._timed_out()
                raise BodyRefused from None
            if message["type"] == "http.disconnect":
                state["left"] = True               # the client went away before its body was whole
            if message["type"] == "http.request":
                state["received"] += len(message.get("body", b""))
                state["body_done"] = not message.get("more_body", False)
                if state["received"] > self.max_body:
                    state["refusal"] = self._too_large()
                    raise BodyRefused
                if delimiter is not None:
                    keep = len(delimiter) + EPILOGUE_BYTES          # the chunk's end only: no copy of a whole chunk
                    if len(head) < HEAD_BYTES:
                        head += message.get("body", b"")[:HEAD_BYTES - len(head)]
                    tail = (tail + message.get("body", b"")[-keep:])[-keep:]
                    if state["body_done"] and (refusal := form_problem(head, tail, delimiter)) is not None:
                        state["refusal"] = refusal
                        raise BodyRefused
            return message

        app = scope.get("app")
        try:
            early = None
            if app is not None:
                check = functools.partial(early_rejection, app.state, scope["method"], scope["path"], headers)
                # The queue's length is the job store's: off the event loop (a stalled store holds this request only).
                queue = (scope["method"], scope["path"]) == ("POST", "/v1/reconstructions")
                early = await to_thread.run_sync(check) if queue else check()
        except ServiceError as exc:            # e.g. the job store does not answer: 503, not a traceback
            early = exc
        except Exception as exc:  # noqa: BLE001 - as below: a problem+json, counted and logged
            log.error("unhandled error", extra={"request_id": rid, "error_type": type(exc).__name__,
                                                "error_at": error_at(exc)})
            early = InternalError()
        length = headers.get("content-length")
        with_body = (length is not None and length.strip() not in ("", "0")) or "chunked" in \
            headers.get("transfer-encoding", "").lower()
        if early is None and with_body and headers.get("content-encoding", "identity").strip().lower() != "identity":
            early = unsupported_coding(headers["content-encoding"])
        held, stopped = False, None
        if early is None and app is not None and (scope["method"], scope["path"]) in PROCESSING_ROUTES:
            early = await take_admission(app.state)      # before its body
            held = early is None and getattr(app.state, "admissions", None) is not None
        try:
            if early is not None:
                await self._problem(emit, rid, early, close=with_body)
            elif length is not None and length.isdigit() and int(length) > self.max_body:
                await self._problem(emit, rid, self._too_large(), close=True)
            else:
                await self.app(scope, limited_receive, send_with_id)
        except BodyRefused:
            if not state["started"]:
                await self._problem(emit, rid, state["refusal"], close=not state["body_done"])
        except asyncio.CancelledError as exc:     # the server stops past its grace: uvicorn cancels what still runs
            stopped = exc
            if not state["started"]:               # a 503 to send again, not uvicorn's plain 500
                try:
                    await self._problem(emit, rid, STOPPING)
                except Exception:  # noqa: BLE001 - the connection is gone: nothing to tell
                    pass
        except Exception as exc:  # noqa: BLE001 - the last line of defence: never a traceback
            log.error("unhandled error", extra={"request_id": rid, "error_type": type(exc).__name__,
                                                "error_at": error_at(exc)})
            if not state["started"]:
                await self._problem(emit, rid, InternalError())
        finally:
            if held:
                app.state.admissions.release()
        path = getattr(scope.get("route"), "path", None) or route_of(app, scope)
        method = sent_method if sent_method in METHODS else "other"
        if state["left"]:
            state["code"] = CLIENT_CLOSED         # whatever the app made of the cut-off body, no one got it
        model = scope["state"].get("model", "")
        elapsed = time.perf_counter() - start
        self.metrics.observe_request(path, method, model, state["code"], elapsed)
        log.info("request", extra={"request_id": rid, "route": path, "method": method,
                                   "status": state["code"], "duration_ms": round(elapsed * 1e3, 1)})
        if stopped is not None:
            raise stopped

    def _too_large(self) -> PayloadTooLarge:
        return PayloadTooLarge(f"the request body (every file of the request together) exceeds the server's limit of "
                               f"{self.max_body / 2**20:.4g} MB (SVRNET_MAX_UPLOAD_MB): send the stacks gzipped "
                               "(.nii.gz), or fewer of them in one request")

    def _timed_out(self) -> RequestTimeout:
        return RequestTimeout(f"the request body did not arrive in time: nothing for {self.idle_s:g} s, or not "
                              f"whole within {self.timeout_s:g} s (SVRNET_UPLOAD_IDLE_S, SVRNET_UPLOAD_TIMEOUT_S)")

    @staticmethod
    async def _problem(send: Send, rid: str, error: ServiceError, close: bool = False) -> None:
        """``error`` as problem+json; ``close``: the request's body is refused unread, so the connection
        closes after the answer (else the server would go on reading, and throwing away, what the
        client goes on sending)."""
        data = json.dumps(problem_body(error.status, error.title, error.detail, error.type, rid)).encode()
        raw = [(b"content-type", MEDIA_TYPE.encode()), (b"content-length", str(len(data)).encode())]
        extra = {**(error.headers or {}), **({"Connection": "close"} if close else {})}
        raw += [(k.lower().encode("latin-1"), v.encode("latin-1")) for k, v in extra.items()]
        await send({"type": "http.response.start", "status": error.status, "headers": raw})
        await send({"type": "http.response.body", "body": data})


def unsupported_coding(coding: str) -> UnsupportedFile:
    """415 for a request body sent with a ``Content-Encoding`` (RFC 9110, 15.5.16): the service reads
    bodies as sent, and a coding it does not undo would reach the form parser as a broken form.

    Example:
        >>> e = unsupported_coding("gzip"); e.status, e.headers["Accept-Encoding"], e.detail[:38]
        (415, 'identity', 'Content-Encoding: gzip: request bodies')
    """
    shown = "".join(c for c in coding if c.isprintable())[:40]
    error = UnsupportedFile(f"Content-Encoding: {shown}: request bodies are read as sent; send the form "
                            "without a content coding (the stacks themselves may be gzipped: .nii.gz)")
    error.headers = {"Accept-Encoding": "identity"}
    return error


STOPPING = NotReady("the server stopped before the answer was ready (it waits for the requests under way, "
                    "then stops them); send the request again")
"""What a request still running when the server stops past its grace is answered (503, ``Retry-After``)."""


class BodyRefused(Exception):
    """Raised inside the app's receive when the body passes a limit (its size or its time)."""
