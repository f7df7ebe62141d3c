"""The choice of job back-end: ``SVRNET_QUEUE_URL`` picks the distributed one; the embedded default
needs neither RQ nor a Redis client (``make serve`` installs neither)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from service.core.settings import Settings
from service.jobs.backends import QUEUE_EXTRA_MISSING, open_backend
from tests.support.local_client import LocalClient

ROOT = Path(__file__).resolve().parents[2]

WITHOUT_QUEUE_PACKAGES = """
import sys, tempfile
sys.modules["rq"] = None          # as if the queue extra were not installed
sys.modules["redis"] = None
from fastapi.testclient import TestClient
from service.core.settings import Settings
from service.main import create_app
from service.inference.registry import ModelRegistry
from tests.api.conftest import OracleEstimator
store = tempfile.TemporaryDirectory(prefix="svrnet-test-")
settings = Settings(data_dir=store.name, queue_url=sys.argv[1] or None)
try:
    with TestClient(create_app(settings, ModelRegistry({"default": OracleEstimator()}))) as client:
        print(client.get("/readyz").status_code, type(client.app.state.job_store).__name__)
except RuntimeError as exc:
    print("error:", exc)
"""


def _run(queue_url: str) -> str:
    out = subprocess.run([sys.executable, "-c", WITHOUT_QUEUE_PACKAGES, queue_url], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.strip().splitlines()[-1]


def test_the_embedded_default_needs_no_queue_packages() -> None:
    assert _run("") == "200 SqliteJobStore"


def test_a_queue_url_without_the_queue_extra_says_what_to_install() -> None:
    assert _run("redis://127.0.0.1:1/0") == "error: " + QUEUE_EXTRA_MISSING.format(name="redis")


@pytest.mark.parametrize("queue_settings", ["embedded", "redis"], indirect=True)
def test_the_queue_url_chooses_the_back_end(queue_settings: dict[str, str]) -> None:
    store, runner = open_backend(Settings(**queue_settings))
    expected = ("RedisJobStore", "RqRunner") if "queue_url" in queue_settings else ("SqliteJobStore", "LocalRunner")
    assert (type(store).__name__, type(runner).__name__) == expected and store.ping()
    runner.shutdown()


def test_an_unreachable_queue_makes_the_replica_unready_not_dead(tmp_path: Path) -> None:
    from service.inference.registry import ModelRegistry
    from service.main import create_app
    from tests.api.conftest import OracleEstimator

    settings = Settings(data_dir=str(tmp_path), queue_url="redis://127.0.0.1:1/0")   # nothing listens there
    with LocalClient(create_app(settings, ModelRegistry({"default": OracleEstimator()})),
                    raise_server_exceptions=False) as client:
        assert client.get("/healthz").status_code == 200
        r = client.get("/readyz")
        assert r.status_code == 503 and "job store" in r.json()["detail"]
        assert client.get("/metrics").status_code == 200      # a scrape does not fail with the queue
        for r in (client.post("/v1/reconstructions", files=[("stacks", ("s.nii.gz", b"x" * 100))]),
                  client.get("/v1/reconstructions/0123456789abcdef0123456789abcdef")):
            assert r.status_code == 503 and r.headers["retry-after"] == "5", r.text
            assert r.json()["type"] == "/problems/store-unavailable" and "Redis" in r.json()["detail"]


def test_a_job_database_that_cannot_be_used_is_503_and_unready(tmp_path: Path) -> None:
    """A data folder turned read-only (or a damaged database) answers reads and fails every write:
    readiness says so, and the job routes answer problem+json 503, counted like any answer."""
    from service.inference.registry import ModelRegistry
    from service.main import create_app
    from tests.api.conftest import OracleEstimator

    settings = Settings(data_dir=str(tmp_path))
    with LocalClient(create_app(settings, ModelRegistry({"default": OracleEstimator()})),
                    raise_server_exceptions=False) as client:
        assert client.get("/readyz").status_code == 200
        store = client.app.state.job_store
        store.db_path = tmp_path / "jobs"                  # a folder: no database opens there
        r = client.get("/readyz")
        assert r.status_code == 503 and "job store" in r.json()["detail"]
        for r in (client.post("/v1/reconstructions", files=[("stacks", ("s.nii.gz", b"x" * 100))]),
                  client.get("/v1/reconstructions/0123456789abcdef0123456789abcdef")):
            assert r.status_code == 503, r.text
            assert r.headers["content-type"] == "application/problem+json"
            assert r.json()["type"] == "/problems/store-unavailable" and "request_id" in r.json()
        counted = [line for line in client.get("/metrics").text.splitlines()
                   if line.startswith("svrnet_requests_total{") and 'status="503"' in line]
        assert counted, "the 503 answers are not counted"
