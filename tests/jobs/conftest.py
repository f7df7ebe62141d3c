"""The job back-ends the tests run against: ``embedded`` (SQLite and the process pool) and ``redis``
(Redis records, the RQ queue, ``svrnet-worker`` processes) on a real ``redis-server``."""

from __future__ import annotations

import os
import signal
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.support.redis_server import SKIP_REASON, RedisServer, redis_server_binary

BACKENDS = ["embedded", "redis"]


@pytest.fixture(scope="session")
def redis_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A real redis-server for the session (skips, with the reason, where there is none; fails instead
    where ``SVRNET_TEST_REQUIRE_REDIS=1``, as ``.ci/run`` sets it where it can install one)."""
    if redis_server_binary() is None:
        if os.environ.get("SVRNET_TEST_REQUIRE_REDIS") == "1":
            pytest.fail(f"SVRNET_TEST_REQUIRE_REDIS=1 and no redis-server: {SKIP_REASON}")
        pytest.skip(SKIP_REASON)
    server = RedisServer(tmp_path_factory.mktemp("redis"))
    try:
        yield server.url
    finally:
        server.stop()


@pytest.fixture
def queue_settings(request: pytest.FixtureRequest, tmp_path: Path) -> dict[str, str]:
    """The settings of one back-end (``request.param``) on a fresh data dir: ``{}`` for the embedded
    one; for ``redis`` a queue of its own on the session's server."""
    if request.param == "embedded":
        return {"data_dir": str(tmp_path / "data")}
    url = request.getfixturevalue("redis_url")
    return {"data_dir": str(tmp_path / "data"), "queue_url": url, "queue_name": f"t{uuid.uuid4().hex[:12]}",
            "queue_maintenance_s": "1", "worker_heartbeat_s": "1", "worker_lost_after_s": "3"}


def env_of(settings: dict[str, str]) -> dict[str, str]:
    return {f"SVRNET_{k.upper()}": str(v) for k, v in settings.items()}


@pytest.fixture
def workers(queue_settings: dict[str, str], tmp_path: Path) -> Iterator[list]:
    """For the redis back-end: one ``svrnet-worker`` on the test's queue (stopped at the end)."""
    from tests.support.live_server import Worker

    started = []
    if "queue_url" in queue_settings:
        started.append(Worker(tmp_path / "worker.log", env_of(queue_settings)))
    yield started
    for w in started:
        w.stop(signal.SIGTERM, timeout=5)               # idle: exits at once; busy: killed after 5 s


@pytest.fixture
def backend(queue_settings: dict[str, str]):  # noqa: ANN201
    """The back-end's job store and runner, as an API replica opens them (shut down after the test)."""
    from service.core.settings import Settings
    from service.jobs.backends import open_backend

    store, runner = open_backend(Settings(**queue_settings))
    yield store, runner
    runner.shutdown()


@pytest.fixture
def store(backend):  # noqa: ANN001, ANN201
    """The job store of the back-end, as a worker or an API replica opens it."""
    return backend[0]
