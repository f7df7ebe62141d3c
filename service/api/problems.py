"""The one place where exceptions become RFC 7807 ``application/problem+json`` responses.

* :class:`ServiceError` subclasses carry their status, title and detail;
* request validation errors (FastAPI) become 400 naming the field (API v1 keeps 422 for unusable files);
* Starlette HTTP errors keep their status (the form parser's 400 is a 507 where the disk filled while it
  spooled the files); a 405 lists every method of the path in ``Allow``, and
  ``OPTIONS`` answers 204 with that ``Allow``;
* anything else is a server fault, answered by :class:`service.api.middleware.RequestContext` (the
  outermost layer) as :class:`~service.core.errors.InternalError`: 500 with the request id, never a traceback.
"""

from __future__ import annotations

import contextlib
import inspect
from http import HTTPStatus

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.api.openapi import allowed_methods
from service.api.stream_messages import STREAM_PATH
from service.core.errors import InsufficientStorage, InvalidParameter, MalformedRequest, PayloadTooLarge, ServiceError
from service.io.limits import raise_if_out_of_space

MEDIA_TYPE = "application/problem+json"
FIELD_LIMIT_KB = inspect.signature(Request.form).parameters["max_part_size"].default // 1024
"""The form parser's limit on a part sent as a plain value, not a file: Starlette's ``max_part_size``,
read from the installed Starlette (the service calls ``request.form()`` with its defaults)."""


def problem_body(status: int, title: str, detail: str, type_: str = "about:blank",
                 request_id: str | None = None) -> dict:
    """The RFC 7807 body (plus the request id, when there is one). A problem of type ``about:blank`` says
    no more than its status, so its title is the status phrase (RFC 9457, 4.2.1); ``detail`` says the rest.

    Example:
        >>> problem_body(404, "Not found", "no route '/x'")["title"]
        'Not Found'
    """
    if type_ == "about:blank":
        with contextlib.suppress(ValueError):
            title = HTTPStatus(status).phrase
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
    """The field a validation error is about, as the client named it (``slice_order[1]``)."""
    out = ""
    for p in loc:
        if p in ("body", "query", "path", "header", "form"):
            continue
        out += f"[{p}]" if isinstance(p, int) else f"{'.' if out else ''}{p}"
    return out or "request"


def _message(error: dict) -> str:
    """A validation error's message in the client's terms: pydantic's ``Value error,`` prefix and
    type names left out."""
    msg = str(error.get("msg", "invalid"))
    if "Expected UploadFile" in msg:
        return "must be a file part (with a filename), not a plain form value"
    return msg.removeprefix("Value error, ")


def _document_problems(app: FastAPI) -> None:
    """Make the OpenAPI page say what the handlers do: errors are ``application/problem+json``, and
    a request that fails validation is a 400 (FastAPI documents its own 422 "Validation Error")."""
    generate = app.openapi

    def openapi() -> dict:
        if app.openapi_schema:
            return app.openapi_schema
        schema = generate()
        known = schema.get("components", {}).get("schemas", {})
        problem_ref = {"schema": {"$ref": "#/components/schemas/Problem"}} if "Problem" in known else {}
        for ops in schema.get("paths", {}).values():
            for op in ops.values():
                responses = op.get("responses", {})
                if responses.get("422", {}).get("description") == "Validation Error":
                    del responses["422"]
                    responses.setdefault("400", {"description": "Bad Request", "content": {MEDIA_TYPE: problem_ref}})
                for code, response in responses.items():
                    content = response.get("content", {})
                    if code[0] in "45" and "application/json" in content:
                        content[MEDIA_TYPE] = content.pop("application/json")
        for name in ("HTTPValidationError", "ValidationError"):
            schema.get("components", {}).get("schemas", {}).pop(name, None)
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]


def install(app: FastAPI) -> None:
    """Register the handlers on ``app`` (and document them in its OpenAPI schema)."""
    _document_problems(app)

    @app.exception_handler(ServiceError)
    async def service_error(request: Request, exc: ServiceError) -> JSONResponse:
        return problem(exc.status, exc.title, exc.detail, exc.type, exc.headers, request)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = exc.errors()
        if any(e.get("type") in ("json_invalid", "value_error.jsondecode") for e in errors):
            return await service_error(request, MalformedRequest("the request body could not be parsed"))
        detail = "; ".join(f"{_field(tuple(e.get('loc', ())))}: {_message(e)}" for e in errors)
        return await service_error(request, InvalidParameter(detail))

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
        if exc.status_code == 404 and exc.detail == "Not Found":     # no route (a route's own 404 is a NotFound)
            path = request.url.path
            if path.endswith("/") and path.strip("/") and allowed_methods(request.app, path):
                return problem(404, "Not Found", f"no route {path[:80]!r}: the route is {path.rstrip('/')[:80]!r}, "
                               "without the trailing slash", request=request)
            if path == STREAM_PATH:
                return problem(426, "Upgrade Required", f"{path}: a WebSocket; connect with ws:// or wss:// (an "
                               "HTTP request with Upgrade: websocket)", headers={"Upgrade": "websocket"},
                               request=request)
            return problem(404, "Not Found", f"no route {path[:80]!r}: the API's routes start with /v1/ "
                           "(the list: /docs); a server URL that ends in /v1 doubles it", request=request)
        if exc.status_code == 405:      # Allow: every method of the path, not only the first route's
            methods = allowed_methods(request.app, request.url.path) or [(exc.headers or {}).get("Allow", "GET")]
            allow = {"Allow": ", ".join(methods)}
            if request.method == "OPTIONS":
                return Response(status_code=204, headers=allow)
            return problem(405, "Method Not Allowed", f"{request.method} is not allowed here; allowed: "
                           f"{allow['Allow']}", headers=allow, request=request)
        if exc.status_code == 400:      # the form parser (a part header over 8 KB, a broken boundary ...)
            try:                        # ... or the disk filling while it spooled the files: not the client's
                raise_if_out_of_space(exc.__cause__)
            except InsufficientStorage as full:
                return await service_error(request, full)
            if "exceeded maximum size" in str(exc.detail):       # a multipart part's or an urlencoded field's
                return await service_error(request, PayloadTooLarge(
                    f"a form field sent as a plain value is over {FIELD_LIMIT_KB} KB: send a large field (poses) as "
                    "a file part of a multipart form (curl: -F poses=@poses.json)"))
            return await service_error(request, MalformedRequest(
                f"the request body could not be parsed ({str(exc.detail).rstrip('.')}): a multipart form's "
                "boundary broken, or a part's header lines too long or too many (a file name of kilobytes)"))
        return problem(exc.status_code, "", str(exc.detail), headers=getattr(exc, "headers", None),
                       request=request)                     # about:blank: the status phrase is the title
