"""A real server stopped mid-job (SIGTERM, or kill -9) leaves no process behind, and the job
completes after a restart. Runs ``svrnet-server``'s code under uvicorn as a subprocess, on a tiny job."""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import httpx
import pytest

from service.jobs.store import SqliteJobStore
from tests.support.live_server import Server
from tests.support.phantoms import orthogonal_stacks_case


@pytest.fixture(scope="module")
def job_files(tmp_path_factory: pytest.TempPathFactory) -> tuple[list, dict]:
    paths, body = orthogonal_stacks_case(tmp_path_factory.mktemp("crash_case"), "Doe_Jane_s")
    files = [part for s, m in paths for part in (("stacks", (s.name, s.read_bytes())), ("masks", (m.name, m.read_bytes())))]
    return files, body


def _status(server: Server, job_id: str) -> dict:
    return httpx.get(f"{server.url}/v1/reconstructions/{job_id}", timeout=10).json()


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=["SIGTERM", "kill-9"])
def test_a_server_stopped_mid_job_leaves_nothing_and_the_job_completes_after_restart(
        tmp_path: Path, job_files: tuple[list, dict], sig: int) -> None:
    files, poses = job_files
    log = tmp_path / "server.log"
    server = Server(tmp_path / "data", log)
    try:
        r = httpx.post(f"{server.url}/v1/reconstructions", files=files + [("poses", ("p.json", json.dumps(poses)))],
                       data={"resolution_mm": "1.5", "svr_iterations": "2", "atlas_frame": "false"}, timeout=60)
        assert r.status_code == 202, r.text
        job_id = r.json()["job_id"]
        deadline = time.time() + 60
        while (st := _status(server, job_id))["status"] == "queued" or st["stage"] in ("starting", "reading"):
            assert time.time() < deadline, st
            time.sleep(0.05)
        assert st["status"] == "running", st                       # stopped mid-job
        server.stop(sig)
        left = server.leftovers()
        assert not left, f"processes left behind after {signal.Signals(sig).name}: {left}"
    finally:
        server.kill_group()
    job = SqliteJobStore(tmp_path / "data").get(job_id)
    assert job is not None and job.status in ("queued", "running") and job.attempts == 1, job
    server = Server(tmp_path / "data", log)
    try:
        deadline = time.time() + 240
        while (st := _status(server, job_id))["status"] not in ("succeeded", "failed", "cancelled"):
            assert time.time() < deadline, st
            time.sleep(0.3)
        assert st["status"] == "succeeded", st
        assert f"re-queued job {job_id}, attempt 2" in log.read_text()
        server.stop(signal.SIGTERM)
        assert not server.leftovers()
    finally:
        server.kill_group()
