"""Dependencies of the routes, as ``Annotated`` aliases (tests override the functions)."""

from __future__ import annotations

import asyncio
import hmac
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import Depends, Header, Request

from service.api.metrics import Metrics
from service.core.errors import Saturated, Unauthorized
from service.core.settings import Settings
from service.inference.registry import ModelRegistry


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_registry(request: Request) -> ModelRegistry:
    return request.app.state.registry


def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


SettingsDep = Annotated[Settings, Depends(get_settings)]
RegistryDep = Annotated[ModelRegistry, Depends(get_registry)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]


def require_api_key(
    settings: SettingsDep,
    authorization: Annotated[str | None, Header(include_in_schema=False)] = None,
    x_api_key: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> None:
    """When ``SVRNET_API_KEYS`` is set: ``Authorization: Bearer <key>`` or ``X-API-Key: <key>``."""
    keys = settings.key_set()
    if not keys:
        return
    given = x_api_key
    if authorization and authorization.lower().startswith("bearer "):
        given = authorization[7:].strip()
    if not given or not any(hmac.compare_digest(given, k) for k in keys):
        raise Unauthorized("Authorization: a valid API key is required (Bearer token or X-API-Key header)")


async def processing_slot(request: Request) -> AsyncIterator[None]:
    """One of ``max_concurrent`` processing slots, or 503 with ``Retry-After`` at once."""
    sem: asyncio.Semaphore = request.app.state.slots
    if sem.locked():
        raise Saturated("the server is busy with other requests; retry later",
                        request.app.state.settings.retry_after_s)
    async with sem:
        yield


ApiKey = Depends(require_api_key)
SlotDep = Annotated[None, Depends(processing_slot)]
