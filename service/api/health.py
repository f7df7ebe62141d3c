"""Liveness and readiness."""

from __future__ import annotations

from anyio import to_thread
from fastapi import APIRouter, Request

from service.api.schemas import problem_responses
from service.api.uploads import scratch_takes_uploads
from service.core.errors import NotReady

router = APIRouter(tags=["operations"])


@router.get("/healthz", summary="Liveness")
async def healthz() -> dict[str, str]:
    """``200 {"status": "ok"}`` while the process serves requests."""
    return {"status": "ok"}


@router.get("/readyz", summary="Readiness", responses=problem_responses(503))
async def readyz(request: Request) -> dict[str, object]:
    """``200`` once every model is loaded, the job store is reachable and the scratch folder takes
    uploads (:func:`~service.api.uploads.scratch_takes_uploads`); ``503`` before. ``workers``:
    how many reconstruction workers serve the queue (0: jobs are accepted and wait for one; null
    where the back-end cannot tell). The API is ready without them: workers scale on their own. A job
    store that does not answer within :data:`~service.jobs.store_probe.PROBE_WAIT_S` is not ready (a
    hung Redis holds a question for its socket timeout; the probe answers all the same)."""
    state = request.app.state
    registry = getattr(state, "registry", None)
    if registry is None or not registry.estimators:
        raise NotReady("no model loaded yet")
    settings = getattr(state, "settings", None)
    if not await to_thread.run_sync(scratch_takes_uploads, None if settings is None else settings.tmp_dir):
        raise NotReady("the scratch folder (SVRNET_TMP_DIR) cannot be written or its disk is full")
    workers = None
    probe = getattr(state, "store_probe", None)
    if probe is not None:                                  # a question to a database or Redis: off the loop
        answer = await to_thread.run_sync(probe)
        if answer is None:
            raise NotReady(f"the job store did not answer within {probe.wait_s:g} s")
        up, workers = answer
        if not up:
            raise NotReady("the job store is not reachable, or its data folder cannot be written or is full")
    return {"status": "ready", "models": sorted(registry.estimators), "workers": workers}
