"""Prometheus metrics of one app instance (its own registry, so several apps can coexist in tests)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Histogram, generate_latest


class Metrics:
    """Requests and latency by route and model, slices processed, slices rejected by reason."""

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

    def observe_request(self, route: str, method: str, model: str, status: int, seconds: float) -> None:
        self.requests.labels(route, method, model, str(status)).inc()
        self.latency.labels(route, model).observe(seconds)

    def observe_slices(self, model: str, reasons: list[str | None]) -> None:
        self.slices.labels(model).inc(len(reasons))
        for r in reasons:
            if r is not None:
                self.rejected.labels(model, r).inc()


router = APIRouter(tags=["operations"])


@router.get("/metrics", summary="Prometheus metrics", response_class=Response)
async def metrics(request: Request) -> Response:
    return Response(generate_latest(request.app.state.metrics.registry), media_type=CONTENT_TYPE_LATEST)
