"""Dependencies of the routes, as ``Annotated`` aliases (tests override the functions)."""

from __future__ import annotations

import asyncio
import hmac
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import Depends, Header, Request
from starlette.datastructures import State

from service.api.metrics import Metrics
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
"""The routes that take a processing slot (:func:`processing_slot`) for as long as they run."""
SLOT_HELD = "processing_slot_held"
"""The request-scope key that says the middleware took the request's slot before its upload was read."""


async def take_slot(state: State) -> Saturated | None:
    """Take one of the processing slots now, before the upload is read: None when taken (the caller
    releases it, ``state.slots.release()``, when the request ends), else 503. Requests that arrive
    together are each given a slot or refused at once (a slot only checked here, and taken once the
    body is in, would let all of them upload before refusing the surplus)."""
    sem: asyncio.Semaphore | None = getattr(state, "slots", None)
    if sem is None:
        return None
    if sem.locked():
        return saturated(state)
    await sem.acquire()          # free: asyncio takes it without waiting, so no other request comes between
    return None


def saturated(state: State) -> Saturated | None:
    """503 when every one of the ``max_concurrent`` processing slots is taken."""
    if state.slots.locked():
        return Saturated("the server is busy with other requests; retry later", state.settings.retry_after_s)
    return None


def queue_full(state: State) -> QueueFull | None:
    """429 when ``max_queued_jobs`` jobs are waiting already."""
    store = getattr(state, "job_store", None)
    settings: Settings = state.settings
    if store is not None and len(store.queued()) >= settings.max_queued_jobs:
        return QueueFull(f"{settings.max_queued_jobs} reconstruction jobs are queued already; retry later",
                         settings.retry_after_s)
    return None


async def processing_slot(request: Request) -> AsyncIterator[None]:
    """One of ``max_concurrent`` processing slots, or 503 with ``Retry-After`` at once; the slot the
    middleware took for the request before its upload was read (:func:`take_slot`), where it did."""
    if request.scope.get("state", {}).get(SLOT_HELD):
        yield
        return
    if (busy := saturated(request.app.state)) is not None:
        raise busy
    sem: asyncio.Semaphore = request.app.state.slots
    async with sem:
        yield


ApiKey = Depends(require_api_key)
MetricsAccess = Depends(require_metrics_access)
SlotDep = Annotated[None, Depends(processing_slot)]
