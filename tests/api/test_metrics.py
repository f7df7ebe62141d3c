"""The app's Prometheus registry: each family once, whatever the app's restarts."""

from __future__ import annotations

from prometheus_client import generate_latest

from service.api.metrics import Metrics


class _Store:
    def __init__(self, succeeded: int) -> None:
        self.succeeded = succeeded

    def ping(self) -> bool:
        return True

    def counts(self) -> dict[str, int]:
        return {"succeeded": self.succeeded}


class _Runner:
    def stats(self) -> dict[str, float]:
        return {"workers": 1.0}


def test_an_app_started_again_reports_its_jobs_once_from_its_new_store() -> None:
    """A lifespan entered twice (a test client opened again, an embedding server restarting the app)
    watches the new store in place of the old one: one ``svrnet_jobs`` family, the new counts."""
    metrics = Metrics()
    metrics.watch_jobs(_Store(2), _Runner())
    metrics.watch_jobs(_Store(5), _Runner())
    text = generate_latest(metrics.registry).decode()
    assert text.count("# TYPE svrnet_jobs gauge") == 1, text
    assert 'svrnet_jobs{status="succeeded"} 5.0' in text and 'svrnet_jobs{status="succeeded"} 2.0' not in text
    assert text.count("# TYPE svrnet_job_store_up gauge") == 1
