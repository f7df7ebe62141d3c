"""Liveness and readiness."""

from __future__ import annotations

from anyio import to_thread
from fastapi import APIRouter, Request

from service.api.schemas import problem_responses
from service.core.errors import NotReady

router = APIRouter(tags=["operations"])


@router.get("/healthz", summary="Liveness")
async def healthz() -> dict[str, str]:
    """``200 {"status": "ok"}`` while the process serves requests."""
    return {"status": "ok"}


@router.get("/readyz", summary="Readiness", responses=problem_responses(503))
async def readyz(request: Request) -> dict[str, object]:
    """``200`` once every model is loaded and the job store is reachable; ``503`` before. ``workers``:
    how many reconstruction workers serve the queue (0: jobs are accepted and wait for one; null
    where the back-end cannot tell). The API is ready without them: workers scale on their own."""
    state = request.app.state
    registry = getattr(state, "registry", None)
    if registry is None or not registry.estimators:
        raise NotReady("no model loaded yet")
    store = getattr(state, "job_store", None)
    if store is not None and not await to_thread.run_sync(store.ping):     # a database query: off the loop
        raise NotReady("the job store is not reachable, or its data folder cannot be written or is full")
    runner = getattr(state, "job_runner", None)
    return {"status": "ready", "models": sorted(registry.estimators),
            "workers": await to_thread.run_sync(runner.live_workers) if runner is not None else None}
