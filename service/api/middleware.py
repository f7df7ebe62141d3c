"""ASGI middleware: request ids, the upload size limit, metrics and access logs."""

from __future__ import annotations

import logging
import re
import time
import uuid

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.metrics import Metrics
from service.api.problems import MEDIA_TYPE

log = logging.getLogger("service.access")
SAFE_ID = re.compile(r"^[A-Za-z0-9._-]{1,64}$")


class RequestContext:
    """Assigns ``X-Request-ID`` (kept from the client when it is a safe token), limits the body
    size (413 before or while reading), records metrics and writes one access-log line."""

    def __init__(self, app: ASGIApp, metrics: Metrics, max_body_bytes: int) -> None:
        self.app, self.metrics, self.max_body = app, metrics, max_body_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        rid = headers.get("x-request-id", "")
        rid = rid if SAFE_ID.match(rid) else uuid.uuid4().hex
        scope.setdefault("state", {})["request_id"] = rid
        start = time.perf_counter()
        status = {"code": 500}

        async def send_with_id(message: Message) -> None:
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
                message.setdefault("headers", [])
                message["headers"] = list(message["headers"]) + [(b"x-request-id", rid.encode())]
            await send(message)

        length = headers.get("content-length")
        if length is not None and length.isdigit() and int(length) > self.max_body:
            await self._too_large(send_with_id, rid)
        else:
            received = {"n": 0}

            async def limited_receive() -> Message:
                message = await receive()
                if message["type"] == "http.request":
                    received["n"] += len(message.get("body", b""))
                    if received["n"] > self.max_body:
                        raise BodyTooLarge
                return message

            try:
                await self.app(scope, limited_receive, send_with_id)
            except BodyTooLarge:
                await self._too_large(send_with_id, rid)
        route = scope.get("route")
        path = getattr(route, "path", None) or "unmatched"
        model = scope["state"].get("model", "")
        elapsed = time.perf_counter() - start
        self.metrics.observe_request(path, scope["method"], model, status["code"], elapsed)
        log.info("request", extra={"request_id": rid, "route": path, "method": scope["method"],
                                   "status": status["code"], "duration_ms": round(elapsed * 1e3, 1)})

    async def _too_large(self, send: Send, rid: str) -> None:
        import json

        body = json.dumps({"type": "/problems/payload-too-large", "title": "Upload too large", "status": 413,
                           "detail": f"the request body exceeds the limit of {self.max_body} bytes",
                           "request_id": rid}).encode()
        await send({"type": "http.response.start", "status": 413,
                    "headers": [(b"content-type", MEDIA_TYPE.encode()), (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})


class BodyTooLarge(Exception):
    """Raised inside the app's receive when the body passes the limit."""
