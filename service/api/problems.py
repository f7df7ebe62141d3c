"""The one place where exceptions become RFC 7807 ``application/problem+json`` responses.

* :class:`ServiceError` subclasses carry their status, title and detail;
* request validation errors (FastAPI) become 400 naming the field (API v1 keeps 422 for unusable files);
* Starlette HTTP errors keep their status;
* anything else is a server fault: 500 with a generic detail and the request id, never a traceback.
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.core.errors import ServiceError

log = logging.getLogger(__name__)
MEDIA_TYPE = "application/problem+json"


def problem_body(status: int, title: str, detail: str, type_: str = "about:blank",
                 request_id: str | None = None) -> dict:
    """The RFC 7807 body (plus the request id, when there is one)."""
    body = {"type": type_, "title": title, "status": status, "detail": detail}
    if request_id:
        body["request_id"] = request_id
    return body


def problem(status: int, title: str, detail: str, type_: str = "about:blank",
            headers: dict[str, str] | None = None, request: Request | None = None) -> JSONResponse:
    rid = getattr(getattr(request, "state", None), "request_id", None)
    return JSONResponse(problem_body(status, title, detail, type_, rid), status_code=status, headers=headers,
                        media_type=MEDIA_TYPE)


def _field(loc: tuple) -> str:
    parts = [str(p) for p in loc if p not in ("body", "query", "path", "header", "form")]
    return ".".join(parts) or "request"


def install(app: FastAPI) -> None:
    """Register the handlers on ``app``."""

    @app.exception_handler(ServiceError)
    async def service_error(request: Request, exc: ServiceError) -> JSONResponse:
        return problem(exc.status, exc.title, exc.detail, exc.type, exc.headers, request)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = exc.errors()
        if any(e.get("type") in ("json_invalid", "value_error.jsondecode") for e in errors):
            return problem(400, "Malformed request", "the request body could not be parsed", request=request)
        detail = "; ".join(f"{_field(tuple(e.get('loc', ())))}: {e.get('msg', 'invalid')}" for e in errors)
        return problem(400, "Invalid parameter", detail, "/problems/invalid-parameter", request=request)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        return problem(exc.status_code, str(exc.detail) if exc.status_code < 500 else "Server error",
                       str(exc.detail), headers=getattr(exc, "headers", None), request=request)

    @app.exception_handler(Exception)
    async def unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.error("unhandled error", extra={"error_type": type(exc).__name__,
                                            "request_id": getattr(request.state, "request_id", None)})
        return problem(500, "Internal server error", "an unexpected error occurred; quote the request id",
                       request=request)
