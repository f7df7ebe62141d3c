"""The distributed back-end end to end: real ``svrnet-server`` replicas and ``svrnet-worker``
processes on one real Redis. Jobs submitted through one replica are polled through the other; a
worker killed with ``kill -9`` mid-job has its job re-delivered to the other worker, which completes
it; SIGTERM lets a worker finish its job; nothing is lost or completed twice."""

from __future__ import annotations

import json
import os
import signal
import time
import uuid
from pathlib import Path

import httpx
import pytest
import redis
from rq.worker import Worker as RqWorker

from tests.jobs.conftest import env_of
from tests.support.live_server import Server, Worker, alive, completions, stop_all
from tests.support.phantoms import orthogonal_stacks_case

FINAL = ("succeeded", "failed", "cancelled")


@pytest.fixture(scope="module")
def job_files(tmp_path_factory: pytest.TempPathFactory) -> list:
    paths, body = orthogonal_stacks_case(tmp_path_factory.mktemp("distributed_case"))
    files = [part for s, m in paths for part in (("stacks", (s.name, s.read_bytes())), ("masks", (m.name, m.read_bytes())))]
    return files + [("poses", ("poses.json", json.dumps(body)))]


@pytest.fixture
def cluster_settings(tmp_path: Path, redis_url: str) -> dict[str, str]:
    return {"data_dir": str(tmp_path / "shared"), "queue_url": redis_url, "queue_name": f"t{uuid.uuid4().hex[:12]}",
            "queue_maintenance_s": "1", "worker_heartbeat_s": "1", "worker_lost_after_s": "3"}


def submit(url: str, files: list, **data: str) -> str:
    # a short job (no atlas-frame step): the tests are about who runs it, not what it computes
    r = httpx.post(f"{url}/v1/reconstructions", files=files,
                   data={"resolution_mm": "1.5", "svr_iterations": "2", "atlas_frame": "false", **data}, timeout=60)
    assert r.status_code == 202, r.text
    return r.json()["job_id"]


def status(url: str, job_id: str) -> dict:
    return httpx.get(f"{url}/v1/reconstructions/{job_id}", timeout=10).json()


@pytest.mark.slow
def test_two_replicas_two_workers_and_a_worker_killed_mid_job(tmp_path: Path, job_files: list,
                                                              cluster_settings: dict[str, str]) -> None:
    env = env_of(cluster_settings)
    apis = [Server(Path(cluster_settings["data_dir"]), tmp_path / f"api{i}.log", **{
        k: v for k, v in cluster_settings.items() if k != "data_dir"}) for i in range(2)]
    logs = [tmp_path / f"worker{i}.log" for i in range(2)]
    workers = [Worker(logs[i], env, "--name", f"w{i}-{cluster_settings['queue_name']}") for i in range(2)]
    conn = redis.Redis.from_url(cluster_settings["queue_url"])
    try:
        jobs = [submit(apis[0].url, job_files) for _ in range(3)]     # one each, and one waiting
        # Wait until worker 0 is inside a job, past reading, then kill it (and only it: its horse must follow).
        deadline, victim, key = time.time() + 90, None, f"rq:worker:w0-{cluster_settings['queue_name']}"
        while victim is None:
            assert time.time() < deadline, [status(apis[1].url, j) for j in jobs]
            worker = RqWorker.find_by_key(key, connection=conn)
            current = worker.get_current_job_id() if worker is not None else None
            if current is not None and (st := status(apis[1].url, current))["status"] == "running" and \
                    st["stage"] not in ("starting", "reading"):
                victim = current
                workers[0].stop(signal.SIGKILL, timeout=10)
            time.sleep(0.05)
        deadline = time.time() + 240
        while not all((st := status(apis[1].url, j))["status"] in FINAL for j in jobs):
            assert time.time() < deadline, st
            time.sleep(0.3)
        final = {j: status(apis[int(j[-1], 16) % 2].url, j) for j in jobs}   # polled through either replica
    finally:
        stop_all(workers, apis)
    assert all(st["status"] == "succeeded" for st in final.values()), final
    assert final[victim]["attempts"] == 2, final[victim]
    assert all(st["attempts"] == 1 for j, st in final.items() if j != victim)
    done = completions(logs)
    assert {j: len(done.get(j, [])) for j in jobs} == {j: 1 for j in jobs}, done     # each completed exactly once
    assert done[victim] == [(1, 2)]                    # completed by worker 1, at attempt 2
    # The killed worker's work horse did not outlive it (it would otherwise finish the job a second time).
    leftovers = [int(p) for p in os.listdir("/proc") if p.isdigit() and
                 f"w0-{cluster_settings['queue_name']}".encode() in Path(f"/proc/{p}/cmdline").read_bytes()]
    assert not [p for p in leftovers if alive(p)]


@pytest.mark.slow
def test_sigterm_lets_the_worker_finish_its_job(tmp_path: Path, job_files: list,
                                                cluster_settings: dict[str, str]) -> None:
    from service.core.settings import Settings
    from service.jobs.backends import open_backend
    from service.jobs.worker_cli import healthy

    settings = Settings(**cluster_settings)
    store, runner = open_backend(settings)
    api = Server(Path(cluster_settings["data_dir"]), tmp_path / "api.log",
                 **{k: v for k, v in cluster_settings.items() if k != "data_dir"})
    assert not healthy(settings)                       # the container health check, before any worker
    worker = Worker(tmp_path / "worker.log", env_of(cluster_settings))
    try:
        deadline = time.time() + 60
        while not healthy(settings):
            assert time.time() < deadline and worker.proc.poll() is None
            time.sleep(0.1)
        job_id = submit(api.url, job_files)
        deadline = time.time() + 60
        while (st := status(api.url, job_id))["status"] == "queued" or st["stage"] in ("starting", "reading"):
            assert time.time() < deadline, st
            time.sleep(0.05)
        code = worker.stop(signal.SIGTERM, timeout=120)        # warm shutdown: the job finishes first
        st = status(api.url, job_id)
    finally:
        worker.kill_group()
        api.stop(signal.SIGTERM)
        api.kill_group()
    assert code == 0 and st["status"] == "succeeded" and st["attempts"] == 1, (code, st)
    assert store.get(job_id).status == "succeeded" and not healthy(settings)
    runner.shutdown()


@pytest.mark.slow
def test_a_second_sigterm_hands_the_job_back_at_once_without_spending_an_attempt(
        tmp_path: Path, job_files: list, cluster_settings: dict[str, str]) -> None:
    """The first SIGTERM asks the worker to finish its job; a second one stops the job and hands it
    back: queued again at once (not once the worker is found lost), shown as queued, the stopped run
    not counted; the next worker completes it as its first attempt."""
    from rq import Queue

    api = Server(Path(cluster_settings["data_dir"]), tmp_path / "api.log",
                 **{k: v for k, v in cluster_settings.items() if k != "data_dir"})
    workers = [Worker(tmp_path / "worker.log", env_of(cluster_settings))]
    try:
        job_id = submit(api.url, job_files)
        deadline = time.time() + 60
        while (st := status(api.url, job_id))["status"] == "queued" or st["stage"] in ("starting", "reading"):
            assert time.time() < deadline, st
            time.sleep(0.05)
        workers[0].proc.send_signal(signal.SIGTERM)
        time.sleep(1.5)                                     # RQ takes two signals within 1 s for one
        workers[0].proc.send_signal(signal.SIGTERM)
        workers[0].proc.wait(timeout=30)
        st = status(api.url, job_id)
        queue = Queue(cluster_settings["queue_name"], connection=redis.Redis.from_url(cluster_settings["queue_url"]))
        assert st["status"] == "queued" and st["attempts"] == 0 and queue.job_ids == [job_id], st
        assert f"handed back job {job_id}" in (tmp_path / "worker.log").read_text()
        workers.append(Worker(tmp_path / "worker2.log", env_of(cluster_settings)))
        deadline = time.time() + 240
        while (st := status(api.url, job_id))["status"] not in FINAL:
            assert time.time() < deadline, st
            time.sleep(0.3)
        assert st["status"] == "succeeded" and st["attempts"] == 1, st
    finally:
        stop_all(workers, [api])


def _run_one(tmp_path: Path, job_files: list, settings: dict[str, str], kill: bool) -> tuple[dict, Path]:
    """One long job on one worker (killed -9 once the job is past reading, if ``kill``): its final
    status and folder."""
    from service.inference.registry import ModelRegistry
    from tests.api.conftest import OracleEstimator, make_client

    with make_client(ModelRegistry({"default": OracleEstimator()}), **settings) as client:
        worker = Worker(tmp_path / "worker.log", env_of(settings))
        try:
            r = client.post("/v1/reconstructions", files=job_files, data={"resolution_mm": "1.0", "svr_iterations": "3"})
            job_id = r.json()["job_id"]
            deadline = time.time() + 60
            while kill and ((st := client.get(f"/v1/reconstructions/{job_id}").json())["status"] == "queued" or
                            st["stage"] in ("starting", "reading")):
                assert time.time() < deadline, st
                time.sleep(0.05)
            if kill:
                worker.stop(signal.SIGKILL)
            deadline = time.time() + 60
            while (st := client.get(f"/v1/reconstructions/{job_id}").json())["status"] not in FINAL:
                assert time.time() < deadline, st
                time.sleep(0.2)
            folder = client.app.state.job_store.directory(job_id)
            deadline = time.time() + 30                  # the status is stored just before the uploads go
            while (folder / "inputs").exists() and time.time() < deadline:
                time.sleep(0.1)
        finally:
            worker.kill_group()
        return st, folder


@pytest.mark.slow
def test_past_the_retry_limit_a_lost_job_fails_with_the_reason(tmp_path: Path, job_files: list,
                                                               cluster_settings: dict[str, str]) -> None:
    st, folder = _run_one(tmp_path, job_files, {**cluster_settings, "job_max_attempts": "1"}, kill=True)
    assert st["status"] == "failed" and st["attempts"] == 1, st
    assert st["error"] == "the worker running it was lost 1 time (SVRNET_JOB_MAX_ATTEMPTS); the job was not completed"
    assert not (folder / "inputs").exists()            # the uploads go when the job ends, whatever the end


@pytest.mark.slow
def test_a_job_past_its_time_limit_is_stopped_and_fails_with_the_reason(tmp_path: Path, job_files: list,
                                                                         cluster_settings: dict[str, str]) -> None:
    st, folder = _run_one(tmp_path, job_files, {**cluster_settings, "job_timeout_h": str(1 / 3600)}, kill=False)
    assert st["status"] == "failed" and st["error"] == "the job ran longer than SVRNET_JOB_TIMEOUT_H and was stopped"
    assert not (folder / "inputs").exists() and not (folder / "outputs" / "volume.nii.gz").exists()


def test_svrnet_worker_runs_several_workers_and_stops_them_all(tmp_path: Path,
                                                               cluster_settings: dict[str, str]) -> None:
    from rq import Queue
    from rq.worker import Worker as RqWorker

    conn = redis.Redis.from_url(cluster_settings["queue_url"])
    queue = Queue(cluster_settings["queue_name"], connection=conn)
    pool = Worker(tmp_path / "pool.log", env_of(cluster_settings), "--workers", "2")
    try:
        deadline = time.time() + 60
        while RqWorker.count(queue=queue) < 2:
            assert time.time() < deadline and pool.proc.poll() is None, (tmp_path / "pool.log").read_text()[-2000:]
            time.sleep(0.1)
        assert pool.stop(signal.SIGTERM, timeout=30) == 0
    finally:
        pool.kill_group()
    assert RqWorker.count(queue=queue) == 0                 # both unregistered on the way out
