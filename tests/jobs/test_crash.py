"""A real server stopped mid-job (SIGTERM, or kill -9) leaves no process behind, and the job
completes after a restart; its job worker killed mid-job is replaced, the job run again (or failed
saying why, past its attempts). Runs ``svrnet-server``'s code under uvicorn as a subprocess, on a tiny job."""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import httpx
import psutil
import pytest

from service.jobs.runner import lost_worker
from service.jobs.sqlite_store import SqliteJobStore
from service.jobs.worker import TIMED_OUT
from tests.support.live_server import Server
from tests.support.phantoms import orthogonal_stacks_case


@pytest.fixture(scope="module")
def job_files(tmp_path_factory: pytest.TempPathFactory) -> tuple[list, dict]:
    paths, body = orthogonal_stacks_case(tmp_path_factory.mktemp("crash_case"), "Doe_Jane_s")
    files = [part for s, m in paths for part in (("stacks", (s.name, s.read_bytes())), ("masks", (m.name, m.read_bytes())))]
    return files, body


def _status(server: Server, job_id: str) -> dict:
    return httpx.get(f"{server.url}/v1/reconstructions/{job_id}", timeout=10).json()


def _running_job(server: Server, job_files: tuple[list, dict], **form: str) -> str:
    """A job submitted with its poses (``form`` its fields) and waited for until it runs: its id."""
    files, poses = job_files
    r = server.post("/v1/reconstructions", files=files + [("poses", ("p.json", json.dumps(poses)))],
                   data={"atlas_frame": "false", **form}, timeout=60)
    assert r.status_code == 202, r.text
    job_id = r.json()["job_id"]
    deadline = time.time() + 60
    while (st := _status(server, job_id))["status"] == "queued" or st["stage"] in ("starting", "reading"):
        assert time.time() < deadline, st
        time.sleep(0.05)
    return job_id


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=["SIGTERM", "kill-9"])
def test_a_server_stopped_mid_job_leaves_nothing_and_the_job_completes_after_restart(
        tmp_path: Path, job_files: tuple[list, dict], sig: int) -> None:
    log = tmp_path / "server.log"
    server = Server(tmp_path / "data", log)
    try:
        job_id = _running_job(server, job_files, resolution_mm="1.5", svr_iterations="2")
        assert _status(server, job_id)["status"] == "running"       # stopped mid-job
        server.stop(sig)
        left = server.leftovers()
        assert not left, f"processes left behind after {signal.Signals(sig).name}: {left}"
    finally:
        server.kill_group()
    job = SqliteJobStore(tmp_path / "data").get(job_id)
    spent = 0 if sig == signal.SIGTERM else 1              # an orderly stop hands the job back without spending a run
    assert job is not None and job.status in ("queued", "running") and job.attempts == spent, job
    server = Server(tmp_path / "data", log)
    try:
        deadline = time.time() + 240
        while (st := _status(server, job_id))["status"] not in ("succeeded", "failed", "cancelled"):
            assert time.time() < deadline, st
            time.sleep(0.3)
        assert st["status"] == "succeeded", st
        assert (f"re-queued job {job_id}, attempt 2" in log.read_text()) == bool(spent)
        assert (f"resumed job {job_id} (stopped at the last shutdown" in log.read_text()) == (not spent)   # either
        server.stop(signal.SIGTERM)
        assert not server.leftovers()
    finally:
        server.kill_group()


@pytest.mark.slow
def test_a_stopping_server_hands_its_running_job_back_at_once_while_requests_finish(
        tmp_path: Path, job_files: tuple[list, dict]) -> None:
    """SIGTERM with a job running and an upload still arriving: the job is back in the queue (no
    attempt spent) and its worker gone within seconds, while the server still waits for the upload;
    the server ends when the upload does."""
    import socket

    server = Server(tmp_path / "data", tmp_path / "server.log")
    try:
        job_id = _running_job(server, job_files, resolution_mm="1.5", svr_iterations="2")
        worker = _job_worker(server)
        upload = socket.create_connection(("127.0.0.1", server.port))
        upload.sendall(b"POST /v1/predict HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: multipart/form-data; boundary=b\r\n"
                       b"Content-Length: 100000\r\n\r\n--b\r\n")           # a body still on its way
        time.sleep(0.5)
        server.proc.send_signal(signal.SIGTERM)
        deadline = time.time() + 15
        store = SqliteJobStore(tmp_path / "data")
        while (job := store.get(job_id)).status == "running" or worker.is_running():
            assert time.time() < deadline, (job, worker)
            time.sleep(0.2)
        assert job.status == "queued" and job.attempts == 0, job
        assert server.proc.poll() is None                               # still waiting for the upload
        upload.close()
        server.proc.wait(timeout=60)
        assert not server.leftovers()
    finally:
        server.kill_group()


def _job_worker(server: Server) -> psutil.Process:
    """The server's job worker process (a spawned pool process, not multiprocessing's resource tracker)."""
    workers = [p for p in psutil.Process(server.proc.pid).children()
               if "spawn_main" in " ".join(p.cmdline()) and "resource_tracker" not in " ".join(p.cmdline())]
    assert len(workers) == 1, [p.cmdline() for p in workers]
    return workers[0]


def _gone(proc: psutil.Process) -> bool:
    """Whether ``proc`` has ended (a zombie not yet reaped by its parent counts as ended)."""
    try:
        return not proc.is_running() or proc.status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


@pytest.mark.slow
@pytest.mark.parametrize("attempts", [2, 1])
def test_a_job_worker_killed_mid_job_is_replaced_and_its_job_runs_again_or_fails_saying_so(
        tmp_path: Path, job_files: tuple[list, dict], attempts: int) -> None:
    # What the kernel's out-of-memory killer does to a worker: the pool it belonged to is broken for
    # good, and without a new one every later job would fail and this one stay 'running'.
    files, poses = job_files
    log = tmp_path / "server.log"
    server = Server(tmp_path / "data", log, job_max_attempts=str(attempts))
    data = {"resolution_mm": "1.5", "svr_iterations": "2", "atlas_frame": "false"}
    try:
        r = server.post("/v1/reconstructions", files=files + [("poses", ("p.json", json.dumps(poses)))],
                       data=data, timeout=60)
        job_id = r.json()["job_id"]
        deadline = time.time() + 60
        while (st := _status(server, job_id))["status"] == "queued" or st["stage"] in ("starting", "reading"):
            assert time.time() < deadline, st
            time.sleep(0.05)
        _job_worker(server).kill()
        deadline = time.time() + 240
        while (st := _status(server, job_id))["status"] not in ("succeeded", "failed", "cancelled"):
            assert time.time() < deadline, st
            time.sleep(0.3)
        if attempts == 2:
            assert st["status"] == "succeeded" and st["attempts"] == 2, st
        else:
            assert st["status"] == "failed" and st["error"] == lost_worker(1), st
        deadline = time.time() + 30                  # the pool logs its replacement after the store says failed
        while "a job worker process was lost" not in log.read_text():
            assert time.time() < deadline, log.read_text()[-2000:]
            time.sleep(0.1)
        again = [json.loads(line) for line in log.read_text().splitlines() if "re-queued job" in line]
        assert [(line["job_id"], line["attempt"]) for line in again] == ([(job_id, 2)] if attempts == 2 else []), again
        r = server.post("/v1/reconstructions", files=files + [("poses", ("p.json", json.dumps(poses)))],
                       data={**data, "svr_iterations": "0"}, timeout=60)
        assert r.status_code == 202, r.text                          # the new pool takes jobs
        deadline = time.time() + 120
        while (st := _status(server, r.json()["job_id"]))["status"] not in ("succeeded", "failed", "cancelled"):
            assert time.time() < deadline, st
            time.sleep(0.3)
        assert st["status"] == "succeeded", st
        server.stop(signal.SIGTERM)
        assert not server.leftovers()
    finally:
        server.kill_group()


@pytest.mark.slow
def test_a_job_past_the_timeout_is_stopped_and_fails_saying_so(tmp_path: Path, job_files: tuple[list, dict]) -> None:
    files, poses = job_files
    server = Server(tmp_path / "data", tmp_path / "server.log", job_timeout_h=str(4 / 3600))
    try:
        r = server.post("/v1/reconstructions", files=files + [("poses", ("p.json", json.dumps(poses)))],
                       data={"resolution_mm": "0.8", "svr_iterations": "8", "atlas_frame": "false"}, timeout=60)  # well past 4 s
        job_id = r.json()["job_id"]
        deadline = time.time() + 60
        while (st := _status(server, job_id))["status"] == "queued":
            assert time.time() < deadline, st
            time.sleep(0.05)
        worker = _job_worker(server)
        while (st := _status(server, job_id))["status"] not in ("succeeded", "failed", "cancelled"):
            assert time.time() < deadline, st
            time.sleep(0.2)
        assert st["status"] == "failed" and st["error"] == TIMED_OUT, st
        inputs = tmp_path / "data" / "jobs" / job_id / "inputs"
        deadline = time.time() + 10                      # the status is stored just before the uploads go
        while inputs.exists() and time.time() < deadline:
            time.sleep(0.1)
        assert not inputs.exists()
        worker.wait(10)                                  # stopped with its job, and the pool replaced
        deadline = time.time() + 10
        while "job workers stopped for a timed-out job and replaced" not in (log := (tmp_path / "server.log").read_text()):
            assert time.time() < deadline
            time.sleep(0.2)
        assert f"job {job_id} failed: {TIMED_OUT}" in log        # the job and why, in the log (JobStore.give_up)
        server.stop(signal.SIGTERM)
        assert not server.leftovers()
    finally:
        server.kill_group()


@pytest.mark.slow
def test_a_running_job_cancelled_stops_at_once_and_the_next_job_runs(tmp_path: Path,
                                                                     job_files: tuple[list, dict]) -> None:
    files, poses = job_files
    log = tmp_path / "server.log"
    server = Server(tmp_path / "data", log)
    upload = files + [("poses", ("p.json", json.dumps(poses)))]
    try:
        job_id = _running_job(server, job_files, resolution_mm="1.0", svr_iterations="3")
        worker = _job_worker(server)
        assert httpx.delete(f"{server.url}/v1/reconstructions/{job_id}", timeout=10).status_code == 204
        # Stopped now, not at the job's next stage: its worker is killed and replaced, unless the job
        # reached a stage's end between the cancel and the kill and stopped there (then the worker,
        # idle, is left alone).
        deadline = time.time() + 10
        while not _gone(worker) and '"job cancelled"' not in log.read_text():
            assert time.time() < deadline
            time.sleep(0.05)
        time.sleep(1)                                    # a kill decided just before the job's own end lands by now
        if _gone(worker):
            deadline = time.time() + 30                  # the replacement's log line
            while "job workers stopped for a cancelled job and replaced" not in log.read_text():
                assert time.time() < deadline
                time.sleep(0.2)
        else:
            assert "job workers stopped" not in log.read_text()
        assert "lost" not in log.read_text()
        time.sleep(1)
        assert _status(server, job_id)["status"] == "cancelled"
        assert not (tmp_path / "data" / "jobs" / job_id).exists()          # nothing written after the cancel
        r = server.post("/v1/reconstructions", files=upload,
                       data={"resolution_mm": "1.5", "svr_iterations": "0", "atlas_frame": "false"}, timeout=60)
        deadline = time.time() + 120
        while (st := _status(server, r.json()["job_id"]))["status"] not in ("succeeded", "failed", "cancelled"):
            assert time.time() < deadline, st
            time.sleep(0.3)
        assert st["status"] == "succeeded" and st["attempts"] == 1, st
        server.stop(signal.SIGTERM)
        assert not server.leftovers()
    finally:
        server.kill_group()
