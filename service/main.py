"""The application factory and its lifespan; nothing else lives here.

Run with ``svrnet-server`` (or ``make serve``); settings come from ``SVRNET_*`` variables.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from anyio import CapacityLimiter
from fastapi import FastAPI
from fastapi_offline import FastAPIOffline

from client.launch import installed_version
from service.api import (health, masks, metrics, models, openapi, predict, problems, reconstructions, stream,
                         stream_messages)
from service.api.access import ListedOriginsCors, needs_key
from service.api.deps import KnownQuery, MetricsAccess
from service.api.metrics import Metrics
from service.api.middleware import RequestContext
from service.api.schemas import problem_responses
from service.api.uploads import sweep_stale_uploads
from service.core import logging as service_logging
from service.core.errors import UnusableModelFile
from service.core.listening import listen_problem
from service.core.machine import cpu_description
from service.core.settings import Settings, load_settings, warn_unknown_variables
from service.core.threads import limit_blas_threads
from service.inference.registry import ModelRegistry
from service.jobs.backends import open_backend, queue_extra_missing
from service.jobs.store_probe import StoreProbe, readiness
from service.preprocess.localise import Localisers
from service.streaming.background import background_executor, stop_stage_process

RETENTION_CHECK_S = 600.0
log = logging.getLogger(__name__)


SHUTDOWN_GRACE_S = 60
"""On SIGTERM the server stops taking connections and gives the requests under way this long to
finish (a predict takes seconds; an upload still arriving after it is cut); running jobs are handed
back to the queue at once, not after that (docs/deployment.md)."""


def create_app(settings: Settings | None = None, registry: ModelRegistry | None = None,
               localisers: Localisers | None = None) -> FastAPI:
    """Build the app; models and localisers load in the lifespan from ``settings.models_dir`` and
    ``settings.localisers_dir`` unless ``registry`` and ``localisers`` are given."""
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        blas = limit_blas_threads(settings.blas_threads)
        app.state.registry = registry or ModelRegistry.from_directory(
            settings.models_dir, settings.default_model, settings.onnx_threads)
        app.state.localisers = localisers if localisers is not None else Localisers.from_directory(
            settings.localisers_dir, settings.onnx_threads)
        app.state.job_store, app.state.job_runner = open_backend(settings)
        app.state.store_probe = StoreProbe(functools.partial(readiness, app.state.job_store, app.state.job_runner))
        await asyncio.to_thread(app.state.job_runner.start)
        app.state.metrics.watch_jobs(app.state.job_store, app.state.job_runner)
        log.info("machine: %s", cpu_description())       # latency depends on it (service/core/machine.py)

        async def upkeep() -> None:
            # Retention everywhere, and the runner's maintenance: with the distributed back-end the
            # queue's (re-delivering the jobs of lost workers), which every replica may do; with the
            # embedded one, stopping jobs past the job timeout; the timeout and the retention each
            # checked ten times within their span, at least every RETENTION_CHECK_S.
            runner_s = settings.queue_maintenance_s if settings.queue_url else settings.job_timeout_h * 360
            period = min(runner_s, RETENTION_CHECK_S, settings.retention_hours * 360)
            while True:
                try:
                    # Folders of requests a killed server left (uploads, decoded DICOM): an hour past
                    # the upload deadline, no request of a live server still uses them.
                    await asyncio.to_thread(sweep_stale_uploads, settings.tmp_dir, settings.upload_timeout_s + 3600)
                    await asyncio.to_thread(app.state.job_store.discard_ended_inputs)   # no upload outlives its job
                    await asyncio.to_thread(app.state.job_store.sweep_orphans, settings.upload_timeout_s + 3600)
                    await asyncio.to_thread(app.state.job_store.expire, settings.retention_hours * 3600)
                    await asyncio.to_thread(app.state.job_runner.maintain)
                except Exception:  # noqa: BLE001 - a store briefly unreachable: /readyz says so; retry
                    log.warning("job upkeep failed; retrying", exc_info=True)
                await asyncio.sleep(period)

        janitor = asyncio.create_task(upkeep())
        try:
            yield
        finally:
            janitor.cancel()
            app.state.job_runner.shutdown()
            try:                                              # a worker stopped as its job ended left them
                app.state.job_store.discard_ended_inputs()
            except Exception:  # noqa: BLE001 - a store unreachable at shutdown: the next start's upkeep does it
                log.warning("uploads of ended jobs not discarded at shutdown", exc_info=True)
            for executor in app.state.stream_stages.values():
                executor.shutdown(wait=False, cancel_futures=True)
            await asyncio.to_thread(stop_stage_process)       # the streams' stack fits: no process left behind
            if blas is not None:
                blas.restore_original_limits()

    # Swagger UI and ReDoc assets are served by the app itself: /docs works without internet access.
    # No redirect of a path with a trailing slash: a 307 makes a client that follows it (curl -L)
    # send a whole upload twice; the 404 names the route instead (service/api/problems.py).
    app = FastAPIOffline(title="SVRnet", version="1.0.0", lifespan=lifespan, redirect_slashes=False,
                  description="Slice-to-atlas pose estimation for fetal MRI with MC-dropout confidence "
                              "(Hou et al., IEEE TMI). Contract: API v1.")
    app.state.settings = settings
    app.state.metrics = Metrics()
    app.state.slots = asyncio.Semaphore(settings.max_concurrent)
    app.state.admissions = asyncio.Semaphore(settings.admissions())
    app.state.registry = None
    app.state.localisers = Localisers({})
    problems.install(app)
    openapi.document_uploads(app, settings.max_files,
                             functools.partial(needs_key, settings) if settings.key_set() else None)
    app.state.stream_sessions = 0
    app.state.metrics.watch_streams(app.state)
    app.state.stream_pose_limiter = CapacityLimiter(settings.stream_workers)
    app.state.stream_stages = {"firm_up": background_executor("svrnet-stream-firm-up"),
                               "end_stack": background_executor("svrnet-stream-end-stack")}
    for module in (health, models, predict, masks, reconstructions):
        app.include_router(module.router, dependencies=[KnownQuery])
    app.include_router(stream.router)
    app.include_router(metrics.router, dependencies=[MetricsAccess, KnownQuery], responses=problem_responses(401))
    app.add_middleware(RequestContext, metrics=app.state.metrics, max_body_bytes=int(settings.max_upload_mb * 2**20),
                       idle_s=settings.upload_idle_s, timeout_s=settings.upload_timeout_s)
    if settings.origin_set():              # outermost: a listed page's preflight carries no key
        app.add_middleware(ListedOriginsCors, origins=settings.origin_set())
    return app


def run(argv: list[str] | None = None) -> None:
    """Console entry point: serve :func:`create_app` with uvicorn on ``SVRNET_HOST:SVRNET_PORT``
    (``--host`` and ``--port`` override them; ``--help`` says so and serves nothing)."""
    import argparse
    import os
    import tempfile

    import uvicorn

    from service.api.http_protocol import with_header_deadline

    parser = argparse.ArgumentParser(
        prog="svrnet-server", description="Serve the SVRnet HTTP API v1 and /v1/stream with the shipped models.",
        epilog="Every other setting (API keys, limits, workers, models folder, job retention) is an SVRNET_* "
               "environment variable: docs/configuration.md.")
    parser.add_argument("--host", help="address to listen on (default: $SVRNET_HOST, else 127.0.0.1)")
    parser.add_argument("--port", type=int, help="port to listen on (default: $SVRNET_PORT, else 8000)")
    parser.add_argument("--version", action="version", version=f"svrnet-server {installed_version() or 'unknown'}")
    args = parser.parse_args(argv)
    given = {k: v for k, v in (("host", args.host), ("port", args.port)) if v is not None}
    settings = load_settings("svrnet-server", **given)
    if problem := listen_problem(settings.host, settings.port):   # before the start, not after it
        raise SystemExit(f"svrnet-server: {problem}")
    if settings.tmp_dir is not None:                            # the form parser spools large uploads there too
        tempfile.tempdir = str(settings.tmp_dir)
        os.environ["TMPDIR"] = str(settings.tmp_dir)
    if settings.queue_url and (missing := queue_extra_missing()):
        parser.exit(1, f"svrnet-server: {missing}\n")
    if not settings.queue_url:                                  # the embedded store: one server owns it
        from service.jobs.local_runner import StoreInUse, lock_store

        try:
            held = lock_store(settings.data_dir)
        except StoreInUse as exc:
            parser.exit(1, f"svrnet-server: {exc}\n")
        if held is not None:
            held.close()                                        # the server's job runner takes it at start
    service_logging.configure(settings.log_level, libraries=("rq",) if settings.queue_url else ())  # its clean-ups
    warn_unknown_variables("svrnet-server")
    if settings.host not in ("127.0.0.1", "localhost", "::1") and not settings.key_set():
        log.warning("serving every host that reaches this address without API keys (SVRNET_API_KEYS)")
    try:                                                        # a broken model file: one line, not a traceback
        registry = ModelRegistry.from_directory(settings.models_dir, settings.default_model, settings.onnx_threads)
        localisers = Localisers.from_directory(settings.localisers_dir, settings.onnx_threads)
    except UnusableModelFile as exc:
        raise SystemExit(f"svrnet-server: {exc}") from None
    if not localisers.localisers:
        log.warning("no brain localiser in SVRNET_LOCALISERS_DIR: every stack needs its mask")
    # uvicorn's own access log writes each raw request path (job ids as sent, anything a client
    # puts in a URL); the service's JSON log records the route instead (service/api/middleware.py).
    app = create_app(settings, registry, localisers)

    class Server(uvicorn.Server):
        def handle_exit(self, sig: int, frame: object) -> None:
            """The first SIGTERM or SIGINT: uvicorn stops taking connections and lets the requests
            under way finish; the running jobs are handed back to the queue now, not after that drain
            (their work would be thrown away, and it would take the cores from the requests)."""
            first = not self.should_exit
            super().handle_exit(sig, frame)
            if first and (runner := getattr(app.state, "job_runner", None)) is not None:
                threading.Thread(target=runner.hand_back, name="job-hand-back", daemon=True).start()

    Server(uvicorn.Config(app, host=settings.host, port=settings.port,
                          log_level=service_logging.server_log_level(settings.log_level),
                          log_config=service_logging.server_log_config(settings.log_level, (stream.STREAM_PATH,)),
                          access_log=False, http=with_header_deadline(settings.header_timeout_s),
                          ws_ping_interval=settings.stream_ping_interval_s, ws_ping_timeout=settings.stream_ping_timeout_s,
                          ws_max_size=stream_messages.largest_frame_bytes(settings.stream_max_pixels),
                          timeout_graceful_shutdown=SHUTDOWN_GRACE_S)).run()


def run_worker() -> None:
    """Console entry point ``svrnet-worker`` (:mod:`service.jobs.worker_cli`); without the ``queue``
    extra it says in one line what to install instead of a traceback."""
    import sys

    if missing := queue_extra_missing():
        sys.exit(f"svrnet-worker: {missing}")
    from service.jobs import worker_cli

    worker_cli.run()
