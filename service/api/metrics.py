"""Prometheus metrics of one app instance (its own registry, so several apps can coexist in tests)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from anyio import to_thread
from fastapi import APIRouter, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily

from service.jobs.store_probe import StoreProbe

if TYPE_CHECKING:
    from starlette.datastructures import State

    from service.jobs.runner import JobRunner
    from service.jobs.store import JobStore


class Metrics:
    """Requests and latency by route and model, slices processed, slices rejected by reason; open
    stream sessions; jobs by state, the runner's figures and whether the job store answers."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter("svrnet_requests_total", "HTTP requests", ["route", "method", "model", "status"],
                                registry=self.registry)
        self.latency = Histogram("svrnet_request_seconds", "HTTP request latency", ["route", "model"],
                                 registry=self.registry,
                                 buckets=(0.01, 0.05, 0.1, 0.25, 0.5, 1, 2, 5, 10, 30, 60, 120))
        self.slices = Counter("svrnet_slices_processed_total", "slices whose pose was estimated", ["model"],
                              registry=self.registry)
        self.rejected = Counter("svrnet_slices_rejected_total", "slices not accepted", ["model", "reason"],
                                registry=self.registry)
        self._jobs: _JobCollector | None = None

    def watch_jobs(self, store: JobStore, runner: JobRunner) -> None:
        """Export the job counts per state and the runner's numbers (workers, queue length), read from
        the store at each scrape: with the distributed back-end every replica reports the whole queue.
        An app started again (its lifespan entered a second time) watches its new store and runner in
        place of the old ones: the scrape holds each family once."""
        if self._jobs is not None:
            self.registry.unregister(self._jobs)
        self._jobs = _JobCollector(store, runner)
        self.registry.register(self._jobs)

    def watch_streams(self, state: State) -> None:
        """Export the open ``/v1/stream`` sessions (``state.stream_sessions``), read at each scrape."""
        Gauge("svrnet_stream_sessions", "open /v1/stream sessions", registry=self.registry).set_function(
            lambda: float(getattr(state, "stream_sessions", 0)))

    def observe_request(self, route: str, method: str, model: str, status: int, seconds: float) -> None:
        self.requests.labels(route, method, model, str(status)).inc()
        self.latency.labels(route, model).observe(seconds)

    def observe_slices(self, model: str, reasons: list[str | None]) -> None:
        self.slices.labels(model).inc(len(reasons))
        for r in reasons:
            if r is not None:
                self.rejected.labels(model, r).inc()


class _JobCollector:
    """The job store's figures at each scrape, asked within :data:`~service.jobs.store_probe.PROBE_WAIT_S`
    (a hung store reads as down, its counts left out, rather than holding the scrape)."""

    def __init__(self, store, runner) -> None:  # noqa: ANN001
        self.store, self.runner = store, runner
        self.probe = StoreProbe(self._figures)

    def _figures(self) -> tuple[bool, dict, dict]:
        try:
            up = bool(self.store.ping())
        except Exception:  # noqa: BLE001 - as below
            up = False
        try:                              # a store that cannot be written (a full disk) still counts
            return up, self.store.counts(), self.runner.stats()
        except Exception:  # noqa: BLE001 - a scrape never fails because the queue is briefly unreachable
            return up, {}, {}

    def collect(self):  # noqa: ANN201
        jobs = GaugeMetricFamily("svrnet_jobs", "reconstruction jobs by state", labels=["status"])
        runner = GaugeMetricFamily("svrnet_job_runner", "job runner figures (workers, queue_length)", labels=["what"])
        up, counts, stats = self.probe() or (False, {}, {})
        yield GaugeMetricFamily("svrnet_job_store_up", "1 while the job store answers and can be written (as /readyz)",
                                value=float(up))
        for status, n in counts.items():
            jobs.add_metric([status], n)
        for what, value in stats.items():
            runner.add_metric([what], value)
        yield jobs
        yield runner


router = APIRouter(tags=["operations"])


@router.get("/metrics", summary="Prometheus metrics", response_class=Response,
            responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}}})
async def metrics(request: Request) -> Response:
    # Off the event loop: its collector asks the job store and the queue, which may stall.
    text = await to_thread.run_sync(generate_latest, request.app.state.metrics.registry)
    return Response(text, media_type=CONTENT_TYPE_LATEST)
