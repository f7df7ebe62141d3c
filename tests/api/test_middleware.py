"""The outermost layer's limits on a request body's time: a stalled or trickling upload gets a 408
problem+json and a closed connection; a slow but steady one, and processing after the body, do not."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import numpy as np

from service.api.metrics import Metrics
from service.api.middleware import RequestContext
from service.inference.registry import ModelRegistry
from tests.api.conftest import make_client
from tests.api.test_predict_errors import nifti_bytes, stack

BOUNDARY = "xx"


def multipart(name: str, filename: str, data: bytes) -> bytes:
    return (f"--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"{name}\"; filename=\"{filename}\"\r\n"
            f"Content-Type: application/octet-stream\r\n\r\n").encode() + data + f"\r\n--{BOUNDARY}--\r\n".encode()


async def call(app: Callable, path: str, body: AsyncIterator[bytes],
               headers: tuple[tuple[bytes, bytes], ...] = ()) -> tuple[int, dict[str, str], bytes]:
    """One POST through the ASGI app, its body's chunks taken from ``body`` as the server would (and
    ``headers`` besides its content type)."""
    sent: list[dict] = []
    done = False

    async def receive() -> dict:
        nonlocal done
        if done:
            await asyncio.sleep(3600)                   # a client that neither sends nor leaves
        try:
            return {"type": "http.request", "body": await body.__anext__(), "more_body": True}
        except StopAsyncIteration:
            done = True
            return {"type": "http.request", "body": b"", "more_body": False}

    async def send(message: dict) -> None:
        sent.append(message)

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST",
             "scheme": "http", "path": path, "raw_path": path.encode(), "query_string": b"", "root_path": "",
             "headers": [(b"content-type", f"multipart/form-data; boundary={BOUNDARY}".encode()), *headers],
             "client": ("127.0.0.1", 1), "server": ("testserver", 80)}
    await asyncio.wait_for(app(scope, receive, send), 30)     # without the limits: a failure, not a hang
    start = next(m for m in sent if m["type"] == "http.response.start")
    headers = {k.decode(): v.decode() for k, v in start["headers"]}
    return start["status"], headers, b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")


def test_a_stalled_body_is_408_and_the_connection_closed(oracle: object) -> None:
    async def stalls() -> AsyncIterator[bytes]:
        yield multipart("stacks", "s.nii.gz", b"\0" * 100)[:80]
        await asyncio.sleep(3600)
        yield b""

    with make_client(ModelRegistry({"default": oracle}), upload_idle_s=0.3) as client:
        t0 = time.perf_counter()
        status, headers, body = client.portal.call(call, client.app, "/v1/predict", stalls())
    assert time.perf_counter() - t0 < 10
    assert status == 408, body
    assert headers["content-type"].startswith("application/problem+json")
    assert headers["connection"] == "close" and headers["x-request-id"]
    problem = json.loads(body)
    assert problem["status"] == 408 and "did not arrive in time" in problem["detail"]
    assert "SVRNET_UPLOAD_IDLE_S" in problem["detail"]


def test_a_body_refused_unread_closes_the_connection(oracle: object) -> None:
    """A body refused before it was read whole (too large by its Content-Length or as it streams in, a
    content coding, no key) is answered with ``Connection: close``: the server would otherwise read,
    and throw away, whatever the client goes on sending on that connection."""
    async def endless() -> AsyncIterator[bytes]:
        yield multipart("stacks", "s.nii.gz", b"").split(b"\r\n--" + BOUNDARY.encode() + b"--")[0]
        while True:                                   # a file that never ends
            yield b"\0" * 4096

    async def form() -> AsyncIterator[bytes]:
        yield multipart("stacks", "s.nii.gz", nifti_bytes(stack()))

    chunked = ((b"transfer-encoding", b"chunked"),)
    with make_client(ModelRegistry({"default": oracle}), max_upload_mb=0.01) as client:
        for body, headers, status in ((endless(), chunked, 413),
                                      (endless(), ((b"content-length", b"1000000000"),), 413),
                                      (form(), ((b"content-encoding", b"gzip"), *chunked), 415)):
            got, answer, text = client.portal.call(call, client.app, "/v1/predict", body, headers)
            assert got == status and answer["connection"] == "close", (got, answer, text[:200])
        problem = json.loads(text)
        assert problem["detail"].startswith("Content-Encoding: gzip:") and answer["accept-encoding"] == "identity"
        got, answer, _ = client.portal.call(call, client.app, "/v1/predict", form(),
                                            ((b"content-encoding", b"identity"), *chunked))
        assert got != 415 and "connection" not in answer
    with make_client(ModelRegistry({"default": oracle}), api_keys="k" * 24) as client:
        got, answer, _ = client.portal.call(call, client.app, "/v1/predict", form(), chunked)
        assert got == 401 and answer["connection"] == "close"


def test_a_form_whose_parts_do_not_start_where_its_boundary_says_is_told_why(oracle: object) -> None:
    """A form sent under another boundary than its ``Content-Type`` names, or with text before its
    first part, is told so (it had been told it was cut off on the way, and to send it again); one
    with an empty line before its first part, as RFC 2046 allows, is read."""
    oracle.truth = np.repeat(np.eye(4)[None], 6, axis=0)
    form = multipart("stacks", "s.nii.gz", nifti_bytes(stack()))
    with make_client(ModelRegistry({"default": oracle})) as client:
        for content_type, body, words in (
                ("multipart/form-data; boundary=other", form, "not separated by the boundary its Content-Type names"),
                (f"multipart/form-data; boundary={BOUNDARY}", b"a note\r\n" + form, "text before its first boundary")):
            r = client.post("/v1/predict", content=body, headers={"content-type": content_type})
            assert r.status_code == 400 and words in r.json()["detail"], r.text[:300]
        r = client.post("/v1/predict", content=b"\r\n" + form,
                        headers={"content-type": f"multipart/form-data; boundary={BOUNDARY}"})
        assert r.status_code == 200, r.text[:300]


def test_a_trickling_body_is_408_at_the_upload_deadline(oracle: object) -> None:
    async def trickles() -> AsyncIterator[bytes]:
        yield multipart("stacks", "s.nii.gz", b"")[:60]
        while True:                                        # a byte every 50 ms: never idle, never whole
            await asyncio.sleep(0.05)
            yield b"\0"

    with make_client(ModelRegistry({"default": oracle}), upload_idle_s=5, upload_timeout_s=0.6) as client:
        t0 = time.perf_counter()
        status, _, body = client.portal.call(call, client.app, "/v1/masks", trickles())
    assert status == 408, body
    assert 0.5 < time.perf_counter() - t0 < 10


def test_a_slow_steady_upload_within_the_limits_is_answered(oracle: object, tmp_path: Path) -> None:
    data = multipart("stacks", "s.nii.gz", nifti_bytes(stack(), tmp=tmp_path))

    async def steady() -> AsyncIterator[bytes]:
        step = len(data) // 6 + 1
        for i in range(0, len(data), step):
            await asyncio.sleep(0.1)
            yield data[i:i + step]

    oracle.truth = np.repeat(np.eye(4)[None], 6, axis=0)
    with make_client(ModelRegistry({"default": oracle}), upload_idle_s=1.0, upload_timeout_s=30) as client:
        status, _, body = client.portal.call(call, client.app, "/v1/predict", steady())   # 0.1 s gaps, 10x slack
    assert status == 200, body
    assert len(json.loads(body)["stacks"][0]["slices"]) == 6


def test_processing_after_the_body_has_no_time_limit() -> None:
    async def slow_app(scope: dict, receive: Callable, send: Callable) -> None:
        while (await receive()).get("more_body"):
            pass
        await asyncio.sleep(0.5)                           # longer than both limits
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"done"})

    async def one_chunk() -> AsyncIterator[bytes]:
        yield f"--{BOUNDARY}--\r\n".encode()                 # a whole (empty) multipart body

    layer = RequestContext(slow_app, Metrics(), max_body_bytes=100, idle_s=0.1, timeout_s=0.2)
    status, _, body = asyncio.run(call(layer, "/anything", one_chunk()))
    assert (status, body) == (200, b"done")


def test_a_client_that_leaves_during_its_upload_is_recorded_as_gone_and_frees_its_admission(oracle: object) -> None:
    """Half a body, then the client is gone: the log and the metrics say 499 (not the 400 the form
    parser makes of what came), and the request's admission is free again."""
    async def leaves(app: Callable) -> None:
        parts = [{"type": "http.request", "body": multipart("stacks", "s.nii.gz", b"\0" * 100)[:80], "more_body": True},
                 {"type": "http.disconnect"}]

        async def receive() -> dict:
            return parts.pop(0) if parts else {"type": "http.disconnect"}

        async def send(message: dict) -> None:
            pass

        scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST",
                 "scheme": "http", "path": "/v1/predict", "raw_path": b"/v1/predict", "query_string": b"",
                 "root_path": "", "client": ("127.0.0.1", 1), "server": ("testserver", 80),
                 "headers": [(b"content-type", f"multipart/form-data; boundary={BOUNDARY}".encode())]}
        await asyncio.wait_for(app(scope, receive, send), 30)

    with make_client(ModelRegistry({"default": oracle}), max_concurrent=1) as client:
        client.portal.call(leaves, client.app)
        scraped = client.get("/metrics").text
        assert client.app.state.slots._value == 1 and client.app.state.admissions._value == 2
    predicts = [line for line in scraped.splitlines()
                if line.startswith("svrnet_requests_total{") and 'route="/v1/predict"' in line]
    assert len(predicts) == 1 and 'status="499"' in predicts[0], predicts


def test_a_header_sent_twice_is_read_as_the_routes_read_it(oracle: object) -> None:
    """The early refusals read a header sent twice by its first value, as the routes' dependencies do
    (Starlette's ``Request.headers``): a request whose first key is wrong is refused before its upload
    is read, and one whose first key is right is not refused by a later copy."""
    with make_client(ModelRegistry({"default": oracle}), api_keys="k1") as client:
        assert client.get("/v1/models", headers=[("X-API-Key", "k1"), ("X-API-Key", "nope")]).status_code == 200
        read: list[bytes] = []

        def body() -> object:
            read.append(b"")
            yield multipart("stacks", "s.nii.gz", nifti_bytes(stack()))

        r = client.post("/v1/predict", content=body(), headers=[
            ("X-API-Key", "nope"), ("X-API-Key", "k1"), ("Content-Type", f"multipart/form-data; boundary={BOUNDARY}")])
        assert r.status_code == 401 and not read, (r.status_code, len(read))


def test_no_answer_may_be_framed_by_another_site_or_sniffed(oracle: object) -> None:
    """The OpenAPI page (whose requests a server without keys serves as its own), its assets, an API
    answer, a route's problem and an early refusal: each forbids framing and type sniffing."""
    with make_client(ModelRegistry({"default": oracle}), api_keys="k1") as client:
        answers = [client.get("/docs"), client.get("/redoc"), client.get("/static-offline-docs/swagger-ui.css"),
                   client.get("/openapi.json"), client.get("/healthz"), client.get("/v1/models"),
                   client.get("/v1/models", headers={"X-API-Key": "k1"}),
                   client.get("/v1/reconstructions/<b>x</b>", headers={"X-API-Key": "k1"})]
    assert [r.status_code for r in answers] == [200, 200, 200, 200, 200, 401, 200, 404]
    for r in answers:
        assert r.headers["x-frame-options"] == "DENY", r.url
        assert r.headers["content-security-policy"] == "frame-ancestors 'none'", r.url
        assert r.headers["x-content-type-options"] == "nosniff", r.url


def test_a_request_the_server_stops_past_its_grace_is_answered_503_and_logged(caplog) -> None:  # noqa: ANN001
    """uvicorn cancels the requests still running when its shutdown grace ends, and answered them a
    plain-text 500 without an access line: the client gets a problem+json 503 to send again, the
    request is counted and logged with that status, and the cancellation goes on."""
    import logging

    running, sent = asyncio.Event(), []

    async def endless_app(scope: dict, receive: Callable, send: Callable) -> None:
        running.set()
        await asyncio.sleep(3600)                          # a request still running at the end of the grace

    async def receive() -> dict:
        return {"type": "http.request", "body": b"", "more_body": False}

    async def send(message: dict) -> None:
        sent.append(message)

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "GET",
             "scheme": "http", "path": "/v1/models", "raw_path": b"/v1/models", "query_string": b"",
             "root_path": "", "headers": [], "client": ("127.0.0.1", 1), "server": ("testserver", 80)}
    metrics = Metrics()
    layer = RequestContext(endless_app, metrics, max_body_bytes=100)

    async def stop_past_grace() -> None:
        task = asyncio.create_task(layer(scope, receive, send))
        await asyncio.wait_for(running.wait(), 10)
        task.cancel(msg="Task cancelled, timeout graceful shutdown exceeded")     # what uvicorn does
        try:
            await task
        except asyncio.CancelledError:
            return
        raise AssertionError("the cancellation was swallowed")

    with caplog.at_level(logging.INFO, logger="service.access"):
        asyncio.run(stop_past_grace())
    start = next(m for m in sent if m["type"] == "http.response.start")
    body = json.loads(b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body"))
    assert start["status"] == 503 and (b"retry-after", b"5") in start["headers"]
    assert body["type"] == "/problems/not-ready" and "send the request again" in body["detail"]
    assert [r.status for r in caplog.records if r.getMessage() == "request"] == [503]
    from prometheus_client import generate_latest

    counted = [line for line in generate_latest(metrics.registry).decode().splitlines()
               if line.startswith("svrnet_requests_total{") and 'status="503"' in line]
    assert counted and counted[0].endswith(" 1.0"), counted
