"""Dependencies of the routes, as ``Annotated`` aliases (tests override the functions)."""

from __future__ import annotations

import asyncio
import hmac
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Annotated

from fastapi import Depends, Header, Request
from starlette.datastructures import State

from service.api.metrics import Metrics
from service.core.cancellation import cancelled_by
from service.core.errors import InvalidParameter, QueueFull, Saturated, ServiceError, Unauthorized
from service.core.settings import Settings
from service.inference.registry import ModelRegistry
from service.preprocess.localise import Localiser, Localisers


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_registry(request: Request) -> ModelRegistry:
    return request.app.state.registry


def get_localisers(request: Request) -> Localisers:
    return request.app.state.localisers


def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


SettingsDep = Annotated[Settings, Depends(get_settings)]
RegistryDep = Annotated[ModelRegistry, Depends(get_registry)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
LocalisersDep = Annotated[Localisers, Depends(get_localisers)]


def localiser_for(localisers: Localisers, masks: list) -> Localiser | None:
    """The default brain localiser for a request whose stacks come without masks (None when masks
    come); a server without one refuses such a request at once, naming the field ``masks``."""
    if masks:
        return None
    if not localisers.localisers:
        raise InvalidParameter("masks: this server has no brain localiser installed; send a mask with every stack")
    return localisers.get()


def api_key_ok(keys: set[str], authorization: str | None, x_api_key: str | None) -> bool:
    """``Authorization: Bearer <key>`` or ``X-API-Key: <key>`` is one of ``keys`` (always true without keys)."""
    if not keys:
        return True
    given = x_api_key
    if authorization and authorization.lower().startswith("bearer "):
        given = authorization[7:].strip()
    return bool(given) and any(hmac.compare_digest(given, k) for k in keys)


UNAUTHORIZED = "Authorization: a valid API key is required (Bearer token or X-API-Key header)"


def require_api_key(
    settings: SettingsDep,
    authorization: Annotated[str | None, Header(include_in_schema=False)] = None,
    x_api_key: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> None:
    """When ``SVRNET_API_KEYS`` is set: ``Authorization: Bearer <key>`` or ``X-API-Key: <key>``."""
    if not api_key_ok(settings.key_set(), authorization, x_api_key):
        raise Unauthorized(UNAUTHORIZED)


def require_metrics_access(
    settings: SettingsDep,
    authorization: Annotated[str | None, Header(include_in_schema=False)] = None,
    x_api_key: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> None:
    """``/metrics`` (routes, status counts, slice reasons per model) needs a key like ``/v1/`` when keys
    are configured, unless ``SVRNET_METRICS_PUBLIC=true``."""
    if not settings.metrics_public:
        require_api_key(settings, authorization, x_api_key)


def needs_key(settings: Settings, path: str) -> bool:
    """Whether ``path`` is protected by the API keys (when some are configured)."""
    return path.startswith("/v1/") or (path == "/metrics" and not settings.metrics_public)


def early_rejection(state: State, method: str, path: str, headers: dict[str, str]) -> ServiceError | None:
    """What can be refused before the upload is read (run by the middleware, so a client without a
    key, or one that would only be told to come back later, does not push its stacks first).

    The route dependencies make the same checks again; these are the early, cheap copies.
    """
    settings: Settings = state.settings
    if needs_key(settings, path) and not api_key_ok(settings.key_set(), headers.get("authorization"),
                                                    headers.get("x-api-key")):
        return Unauthorized(UNAUTHORIZED)
    if method == "POST" and path == "/v1/reconstructions":
        return queue_full(state)
    return None


SLOT_ROUTES = frozenset({("POST", "/v1/predict"), ("POST", "/v1/masks"), ("POST", "/v1/reconstructions")})
"""The routes that are admitted before their upload is read (:func:`take_admission`) and take a
processing slot (:func:`processing_slot`) once it is in."""


async def take_admission(state: State) -> Saturated | None:
    """Admit a request to a processing route now, before its upload is read: None when admitted (the
    caller releases it, ``state.admissions.release()``, when the request ends), else 503 at once.

    Admissions (``max_admitted``) bound what is received, waiting and processed at once -- the
    spooled uploads on disk among them -- so requests that arrive together beyond them are refused
    before they push their stacks. Processing slots (``max_concurrent``) are taken only once a body
    is whole (:func:`processing_slot`): a client whose upload trickles in holds an admission, never the
    processing a quicker client's request needs."""
    sem: asyncio.Semaphore | None = getattr(state, "admissions", None)
    if sem is None:
        return None
    if sem.locked():
        return Saturated("the server is busy with other requests; retry later", state.settings.retry_after_s)
    await sem.acquire()          # free: asyncio takes it without waiting, so no other request comes between
    return None


async def processing_slot(request: Request) -> AsyncIterator[None]:
    """One of ``max_concurrent`` processing slots, taken once the request's upload is in (FastAPI reads
    the body before it solves the dependencies): waited for up to ``slot_wait_s``, in arrival order,
    then 503 with ``Retry-After``."""
    state = request.app.state
    sem: asyncio.Semaphore = state.slots
    try:
        await asyncio.wait_for(sem.acquire(), timeout=state.settings.slot_wait_s)
    except asyncio.TimeoutError:
        raise Saturated("every processing slot stayed busy while this request waited; retry later",
                        state.settings.retry_after_s) from None
    try:
        yield
    finally:
        sem.release()


@asynccontextmanager
async def stopped_when_client_leaves(request: Request) -> AsyncIterator[threading.Event]:
    """Within the block, the stages a route runs stop at their next checkpoint once the client has
    closed its connection (:mod:`service.core.cancellation`): a request whose client left gives its
    processing slot back within a step, not at the end of work no one will read. A task listens for
    the ASGI ``http.disconnect`` (after the body is in, the server's next message is that one)."""
    gone = threading.Event()

    async def listen() -> None:
        while (await request.receive())["type"] != "http.disconnect":
            pass
        gone.set()

    listener = asyncio.create_task(listen())
    try:
        with cancelled_by(gone):
            yield gone
    finally:
        listener.cancel()


def queue_full(state: State) -> QueueFull | None:
    """429 when ``max_queued_jobs`` jobs are waiting already."""
    store = getattr(state, "job_store", None)
    settings: Settings = state.settings
    if store is not None and len(store.queued()) >= settings.max_queued_jobs:
        return QueueFull(f"{settings.max_queued_jobs} reconstruction jobs are queued already; retry later",
                         settings.retry_after_s)
    return None


ApiKey = Depends(require_api_key)
MetricsAccess = Depends(require_metrics_access)
SlotDep = Annotated[None, Depends(processing_slot)]
