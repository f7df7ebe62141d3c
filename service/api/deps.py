"""Dependencies of the routes, as ``Annotated`` aliases (tests override the functions)."""

from __future__ import annotations

import asyncio
import hashlib
import threading
from collections import Counter
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Annotated

from fastapi import Depends, Header, Request
from fastapi.dependencies.models import Dependant
from starlette.datastructures import State

from service.api.access import (FOREIGN_HOST, FOREIGN_ORIGIN, UNAUTHORIZED, api_key_ok, key_owner, needs_key, origin_ok,
                                presented_key)
from service.api.metrics import Metrics
from service.core.cancellation import cancelled_by
from service.core.errors import (ClientGone, ForeignOrigin, InvalidParameter, QueueFull, Saturated, ServiceError,
                                 Unauthorized)
from service.core.names import shown_name
from service.core.process_pools import trim_heap
from service.core.settings import Settings
from service.inference.registry import ModelRegistry
from service.preprocess.localise import Localiser, Localisers


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_registry(request: Request) -> ModelRegistry:
    return request.app.state.registry


async def get_localisers(request: Request) -> Localisers:
    return request.app.state.localisers


async def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


SettingsDep = Annotated[Settings, Depends(get_settings)]
RegistryDep = Annotated[ModelRegistry, Depends(get_registry)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
LocalisersDep = Annotated[Localisers, Depends(get_localisers)]


def requested_model(request: Request, registry: ModelRegistry, name: str) -> str:
    """The pose model ``name`` means (:meth:`~service.inference.registry.ModelRegistry.resolve`),
    recorded as the request's ``model`` label in the metrics from here on."""
    model = registry.resolve(name)
    request.scope["state"]["model"] = model
    return model


def localiser_for(localisers: Localisers, masks: list) -> Localiser | None:
    """The default brain localiser for a request whose stacks come without masks (None when masks
    come); a server without one refuses such a request at once, naming the field ``masks``."""
    if masks:
        return None
    if localisers.default() is None:
        raise InvalidParameter("masks: this server has no brain localiser named default installed; send a mask with "
                               "every stack")
    return localisers.default()


def localiser_for_regions(localisers: Localisers, uploads: list) -> Localiser | None:
    """The default brain localiser where an upload's mask is a region of interest around the head (or
    it came without one), the brain to be found in it; None where every upload has its brain mask. A
    server without one refuses such a request, naming the field ``masks``."""
    if not any(u.localised for u in uploads):
        return None
    if localisers.default() is None:
        raise InvalidParameter("masks: a mask that is a box around the head asks for the brain to be found in it, and "
                               "this server has no brain localiser named default; send brain masks")
    return localisers.default()


async def require_api_key(
    settings: SettingsDep,
    authorization: Annotated[str | None, Header(include_in_schema=False)] = None,
    x_api_key: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> None:
    """When ``SVRNET_API_KEYS`` is set: ``Authorization: Bearer <key>`` or ``X-API-Key: <key>``.

    This dependency and the others of this module that read the app's state do no I/O: they run on
    the event loop (``async def``), so no request waits for a thread of anyio's pool to be let in,
    whatever holds those threads (calls to a stalled job store)."""
    if not api_key_ok(settings.key_set(), authorization, x_api_key):
        raise Unauthorized(UNAUTHORIZED)


async def require_metrics_access(
    settings: SettingsDep,
    authorization: Annotated[str | None, Header(include_in_schema=False)] = None,
    x_api_key: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> None:
    """``/metrics`` (routes, status counts, slice reasons per model) needs a key like ``/v1/`` when keys
    are configured, unless ``SVRNET_METRICS_PUBLIC=true``."""
    if not settings.metrics_public:
        await require_api_key(settings, authorization, x_api_key)


IDEMPOTENCY_HEADER = "Idempotency-Key"
"""A request header of ``POST /v1/reconstructions``: a client's random key for one submission, sent
again with every retry of it, so that a retry whose first answer was lost returns the job the first
made instead of starting a second."""


def idempotency_digest(key: str | None, owner: str = "") -> str | None:
    """The digest a job keeps of an ``Idempotency-Key`` (none of the client's text is stored), or None;
    :class:`InvalidParameter` for a key that is not 8 to 200 printable ASCII characters. ``owner``,
    the API key the submission presents, scopes it: one client's key never matches, nor names,
    another client's job.

    Example:
        >>> idempotency_digest("4f1c2a9e0b7d"), idempotency_digest(None)
        ('0ffe3575cb6c496d947afe5441358c1720b414d1c3a8857562c43469609125af', None)
        >>> idempotency_digest("4f1c2a9e0b7d", owner="k-1") != idempotency_digest("4f1c2a9e0b7d", owner="k-2")
        True
    """
    if key is None:
        return None
    if not 8 <= len(key) <= 200 or not all("!" <= c <= "~" for c in key):
        raise InvalidParameter(f"{IDEMPOTENCY_HEADER}: 8 to 200 printable ASCII characters, the same for every "
                               "retry of one submission")
    scoped = key if not owner else key_owner(owner) + "\0" + key
    return hashlib.sha256(scoped.encode()).hexdigest()


def early_rejection(state: State, method: str, path: str, headers: dict[str, str]) -> ServiceError | None:
    """What can be refused before the upload is read (run by the middleware, so a client without a
    key, or one that would only be told to come back later, does not push its stacks first).

    The route dependencies make the same checks again; these are the early, cheap copies.
    """
    settings: Settings = state.settings
    if path.startswith("/v1/") and not origin_ok(settings, headers):      # the API: probes and docs stay open
        return ForeignOrigin(FOREIGN_ORIGIN if "origin" in headers else FOREIGN_HOST)
    if needs_key(settings, path) and not api_key_ok(settings.key_set(), headers.get("authorization"),
                                                    headers.get("x-api-key")):
        return Unauthorized(UNAUTHORIZED)
    if method == "POST" and path == "/v1/reconstructions":
        key = headers.get("idempotency-key")
        if key is not None:
            try:
                digest = idempotency_digest(key.strip(), presented_key(headers.get("authorization"),
                                                                       headers.get("x-api-key")))
            except InvalidParameter as exc:
                return exc
            store = getattr(state, "job_store", None)
            if store is not None and store.job_for_key(digest) is not None:
                return None            # a retry: the route answers with the job its key made, queue full or not
        return queue_full(state)
    return None


PROCESSING_ROUTES = frozenset({("POST", "/v1/predict"), ("POST", "/v1/masks"), ("POST", "/v1/reconstructions")})
"""The routes that are admitted before their upload is read (:func:`take_admission`) and take a
processing slot (:func:`processing`) once it is in and valid."""


async def take_admission(state: State) -> Saturated | None:
    """Admit a request to a processing route now, before its upload is read: None when admitted (the
    caller releases it, ``state.admissions.release()``, when the request ends), else 503 at once.

    Admissions (``max_admitted``) bound what is received, waiting and processed at once -- the
    spooled uploads on disk among them -- so requests that arrive together beyond them are refused
    before they push their stacks. Processing slots (``max_concurrent``) are taken only once a body
    is whole and valid (:func:`processing`): a client whose upload trickles in holds an admission, never the
    processing a quicker client's request needs."""
    sem: asyncio.Semaphore | None = getattr(state, "admissions", None)
    if sem is None:
        return None
    if sem.locked():
        return Saturated("the server is busy with other requests; retry later", state.settings.retry_after_s)
    await sem.acquire()          # free: asyncio takes it without waiting, so no other request comes between
    return None


def _drop(slots: asyncio.Semaphore, acquire: asyncio.Future) -> None:
    """Give back the slot a waiter got, or stop it waiting (a waiter cancelled after its wake-up gives
    the slot on to the next)."""
    if acquire.done() and not acquire.cancelled():
        slots.release()
    else:
        acquire.cancel()


async def _wait_for_slot(slots: asyncio.Semaphore, wait_s: float, left: asyncio.Event) -> str:
    """One of ``slots``: at once where one is free, else waited for up to ``wait_s`` (in arrival order)
    unless the client leaves first; returns ``held``, ``busy`` (none came free) or ``gone`` (the
    client left: no slot held). A request cancelled meanwhile (a server shutting down) holds none."""
    if not slots.locked():
        await slots.acquire()               # free: asyncio takes it without waiting
        return "held"
    if wait_s <= 0:
        return "busy"
    acquire, leaving = asyncio.ensure_future(slots.acquire()), asyncio.ensure_future(left.wait())
    try:
        await asyncio.wait({acquire, leaving}, timeout=wait_s, return_when=asyncio.FIRST_COMPLETED)
    except BaseException:
        _drop(slots, acquire)
        raise
    finally:
        leaving.cancel()
    if left.is_set():
        _drop(slots, acquire)
        return "gone"
    if acquire.done() and not acquire.cancelled():
        return "held"
    acquire.cancel()
    return "busy"


@asynccontextmanager
async def processing(request: Request, answer_only: bool = True) -> AsyncIterator[None]:
    """A request's processing, around the work of a route's body (entered there, so after FastAPI has
    read the upload and checked every field: an invalid request gets its 400 without waiting):

    * one of ``max_concurrent`` processing slots, waited for up to ``slot_wait_s`` in arrival order,
      then 503 with ``Retry-After``; given back when the work ends, before the answer is sent (a
      client that reads its answer slowly holds no slot);
    * the work stops at its next checkpoint once the client has closed its connection
      (:mod:`service.core.cancellation`; 499; where the work makes nothing but the answer,
      ``answer_only``, one that leaves during the last step is a 499 as its work ends: a job's
      submission stands once it is queued, answered or not), and a client that leaves while its request waits for a
      slot ends the wait. A task listens for the ASGI ``http.disconnect`` (once the body is in, the
      server's next message is that one)."""
    state = request.app.state
    gone, left = threading.Event(), asyncio.Event()

    async def listen() -> None:
        while (await request.receive())["type"] != "http.disconnect":
            pass
        gone.set()
        left.set()

    listener = asyncio.create_task(listen())
    try:
        got = await _wait_for_slot(state.slots, state.settings.slot_wait_s, left)
        if got == "busy":
            raise Saturated("every processing slot stayed busy while this request waited; retry later",
                            state.settings.retry_after_s)
        if got == "gone":
            raise ClientGone()
        state.processing_now = getattr(state, "processing_now", 0) + 1
        try:
            with cancelled_by(gone):
                yield
            if answer_only and gone.is_set():   # it left during the last step, past every checkpoint
                raise ClientGone()
        finally:
            state.slots.release()
            state.processing_now -= 1
            if not state.processing_now:
                asyncio.get_running_loop().call_later(TRIM_AFTER_S, _trim_if_idle, state)
    finally:
        listener.cancel()


TRIM_AFTER_S = 1.0
"""How long after the last request's processing ends the server trims its heap (:func:`_trim_if_idle`):
its answer has been built and sent by then, and the arrays it held are freed."""


def _trim_if_idle(state: State) -> None:
    """Hand the heap's free pages back (:func:`~service.core.process_pools.trim_heap`, in a thread) where
    no request has begun processing meanwhile: a request's peak is not kept by an idle server; none where
    the server is stopping (its threads' executor shut down)."""
    if not getattr(state, "processing_now", 0):
        try:
            asyncio.get_running_loop().run_in_executor(None, trim_heap)
        except RuntimeError:                       # the executor shut down: the process ends, its heap with it
            pass


def queue_full(state: State) -> QueueFull | None:
    """429 when ``max_queued_jobs`` jobs are waiting already: the early answer, before an upload is
    read or hashed. The store checks again as it adds the job (:meth:`~service.jobs.store.JobStore.create_once`),
    so that submissions arriving together never queue more."""
    store = getattr(state, "job_store", None)
    settings: Settings = state.settings
    if store is not None and len(store.queued()) >= settings.max_queued_jobs:
        return full_queue(settings)
    return None


def full_queue(settings: Settings) -> QueueFull:
    """The 429 of a queue that holds ``max_queued_jobs``, with the server's ``Retry-After``."""
    return QueueFull.holding(settings.max_queued_jobs, settings.retry_after_s)


ApiKey = Depends(require_api_key)
MetricsAccess = Depends(require_metrics_access)


def query_names(dependant: Dependant) -> list[str]:
    """The query parameters a route declares, its dependencies' included (by the names clients send)."""
    return [p.alias for p in dependant.query_params] + [n for d in dependant.dependencies for n in query_names(d)]


async def known_query(request: Request) -> None:
    """Refuses (400, by name) a query parameter the route does not declare, and one given twice: a
    misspelt ``?stak=0`` would otherwise be ignored (the volume served in atlas space) and a doubled
    one decided by its last copy. Routes with a body take their options in it, and declare none here.

    Async, so that it runs on the event loop (it reads no file, no store): a route whose only
    dependency it is -- ``/healthz`` -- needs no worker thread, and is answered while calls to a
    stalled job store hold every one of them.
    """
    route = request.scope.get("route")
    dependant = getattr(route, "dependant", None)
    declared = query_names(dependant) if dependant is not None else []
    given = [k for k, _ in request.query_params.multi_items()]
    unknown = [k for k in dict.fromkeys(given) if k not in declared]
    if unknown:
        body = request.method in ("POST", "PUT", "PATCH")
        takes = f"this route takes {', '.join(declared)}" if declared else \
            "this route takes none" + (" (its options go in the body)" if body else "")
        raise InvalidParameter(f"{shown_name(unknown[0])}: unknown query parameter; {takes}")
    doubled = [(k, n) for k, n in Counter(given).items() if n > 1]
    if doubled:
        raise InvalidParameter(f"{doubled[0][0]}: given {doubled[0][1]} times; this query parameter takes one value")


KnownQuery = Depends(known_query)
