"""The distributed job back-end, measured (issue 14): real ``svrnet-server`` processes, real
``svrnet-worker`` processes, a real ``redis-server``.

1. **Submit-to-start latency** (``started_at - submitted_at`` of each job, from the store): small jobs
   one after the other on idle workers, embedded back-end vs Redis + RQ; the difference is what the
   queue adds.
2. **Two replicas, two workers, one killed**: ``--jobs`` jobs submitted through replica A (alternately
   through B), polled through the other; ``kill -9`` of one worker mid-job. Every job must end
   ``succeeded``; each is completed exactly once (the workers' logs), the killed one by the other
   worker at attempt 2. The kill comes once a quarter of the jobs are done.

    .venv/bin/python benchmarks/queue_bench.py [--jobs 20] [--latency-jobs 15]
"""

from __future__ import annotations

import argparse
import json
import signal
import statistics
import sys
import tempfile
import time
import uuid
from collections import Counter
from datetime import timezone
from pathlib import Path

import httpx
import redis
from rq.job import Job as RqJob
from rq.worker import Worker as RqWorker

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.core.machine import cpu_description  # noqa: E402
from service.core.settings import Settings  # noqa: E402
from service.jobs.backends import open_backend  # noqa: E402
from tests.support.live_server import Server, Worker, completions, stop_all  # noqa: E402
from tests.support.phantoms import orthogonal_stacks_case  # noqa: E402
from tests.support.redis_server import RedisServer  # noqa: E402

FINAL = ("succeeded", "failed", "cancelled")


def _files(folder: Path) -> list:
    folder.mkdir(parents=True)
    paths, body = orthogonal_stacks_case(folder)
    files = [p for s, m in paths for p in (("stacks", (s.name, s.read_bytes())), ("masks", (m.name, m.read_bytes())))]
    return files + [("poses", ("poses.json", json.dumps(body)))]


def _submit(url: str, files: list, **data: str) -> str:
    r = httpx.post(f"{url}/v1/reconstructions", files=files, data=data, timeout=60)
    r.raise_for_status()
    return r.json()["job_id"]


def _wait(url: str, job_id: str, timeout: float = 600) -> dict:
    deadline = time.time() + timeout
    while (st := httpx.get(f"{url}/v1/reconstructions/{job_id}", timeout=10).json())["status"] not in FINAL:
        if time.time() > deadline:
            raise TimeoutError(st)
        time.sleep(0.05)
    return st


def latency(files: list, folder: Path, settings: dict[str, str], n: int) -> list[float]:
    """Submit-to-start latencies (ms) of ``n`` small jobs, one at a time."""
    folder.mkdir(parents=True)
    server = Server(Path(settings["data_dir"]), folder / "api.log", **{k: v for k, v in settings.items() if k != "data_dir"})
    worker = Worker(folder / "worker.log", {f"SVRNET_{k.upper()}": v for k, v in settings.items()}) \
        if "queue_url" in settings else None
    store, runner = open_backend(Settings(**settings))
    out = []
    try:
        for i in range(n + 1):
            job_id = _submit(server.url, files, resolution_mm="3.0", svr_iterations="0")
            assert _wait(server.url, job_id)["status"] == "succeeded"
            job = store.get(job_id)
            if i:                                      # the first one warms the worker up
                out.append(1000 * (job.started_at - job.submitted_at))
            time.sleep(0.3)                            # idle again
    finally:
        if worker is not None:
            worker.stop(signal.SIGTERM, timeout=30)
        server.stop(signal.SIGTERM)
        server.kill_group()
        runner.shutdown()
    return out


def _p90(ms: list[float]) -> float:
    return statistics.quantiles(ms, n=10, method="inclusive")[-1]


def _summary(ms: list[float]) -> str:
    return f"median {statistics.median(ms):6.1f} ms, p90 {_p90(ms):6.1f} ms, max {max(ms):6.1f} ms (n={len(ms)})"


def cluster(files: list, folder: Path, settings: dict[str, str], n_jobs: int) -> None:
    folder.mkdir(parents=True)
    env = {f"SVRNET_{k.upper()}": v for k, v in settings.items()}
    apis = [Server(Path(settings["data_dir"]), folder / f"api{i}.log",
                   **{k: v for k, v in settings.items() if k != "data_dir"}) for i in range(2)]
    logs = [folder / f"worker{i}.log" for i in range(2)]
    names = [f"w{i}-{settings['queue_name']}" for i in range(2)]
    workers = [Worker(logs[i], env, "--name", names[i]) for i in range(2)]
    conn = redis.Redis.from_url(settings["queue_url"])
    t0 = time.time()
    try:
        jobs = [_submit(apis[i % 2].url, files, resolution_mm="1.5", svr_iterations="2") for i in range(n_jobs)]
        victim = None
        while victim is None:      # once a quarter of the jobs are done, worker 0 inside a job, past reading: kill it
            done = sum(httpx.get(f"{apis[1].url}/v1/reconstructions/{j}", timeout=10).json()["status"] == "succeeded"
                       for j in jobs)
            current = RqWorker.find_by_key(f"rq:worker:{names[0]}", connection=conn).get_current_job_id() \
                if done >= n_jobs // 4 else None
            if current is not None:
                st = httpx.get(f"{apis[1].url}/v1/reconstructions/{current}", timeout=10).json()
                if st["status"] == "running" and st["stage"] not in ("starting", "reading"):
                    victim, killed_at = current, time.time()
                    workers[0].stop(signal.SIGKILL, timeout=10)
            time.sleep(0.05)
        final = {j: _wait(apis[(k + 1) % 2].url, j) for k, j in enumerate(jobs)}
        wall = time.time() - t0
        store, runner = open_backend(Settings(**settings))
        reclaimed = store.get(victim).started_at - killed_at
        requeued = RqJob.fetch(victim, connection=conn).enqueued_at.replace(tzinfo=timezone.utc).timestamp() - killed_at
        runner.shutdown()
    finally:
        stop_all(workers, apis, timeout=60)
    done = {j: [f"w{i}#{a}" for i, a in runs] for j, runs in completions(logs).items()}
    states = Counter(st["status"] for st in final.values())
    once = sum(len(done.get(j, [])) == 1 for j in jobs)
    print(f"\n2 replicas, 2 workers, {n_jobs} jobs (1.5 mm, 2 SVR rounds), worker 0 killed -9 mid-job:")
    print(f"  final states: {dict(states)}; attempts: {dict(Counter(st['attempts'] for st in final.values()))}")
    print(f"  completed exactly once: {once}/{n_jobs}; the killed job completed by {done.get(victim)} (worker#attempt)")
    print(f"  the killed job back in the queue {requeued:.1f} s after the kill (lost-after "
          f"{settings['worker_lost_after_s']} s + heartbeat {settings['worker_heartbeat_s']} s + maintenance every "
          f"{settings['queue_maintenance_s']} s), started again {reclaimed:.1f} s after it (behind the jobs queued before)")
    print(f"  jobs per worker: {dict(Counter(c.split('#')[0] for v in done.values() for c in v))}; wall {wall:.1f} s")
    assert states == {"succeeded": n_jobs} and once == n_jobs, (states, done)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=20)
    ap.add_argument("--latency-jobs", type=int, default=15)
    args = ap.parse_args()
    print(f"machine: {cpu_description()}")
    scratch = tempfile.TemporaryDirectory(prefix="svrnet-queue-bench-")
    root = Path(scratch.name)
    files = _files(root / "case")
    server = RedisServer(root / "redis")
    try:
        queue = {"queue_url": server.url, "queue_maintenance_s": "5", "worker_heartbeat_s": "5", "max_queued_jobs": "32",
                 "worker_lost_after_s": "15"}
        print("submit-to-start latency, small jobs one at a time on an idle worker:")
        embedded = latency(files, root / "emb", {"data_dir": str(root / "emb-data")}, args.latency_jobs)
        print(f"  embedded (SQLite + process pool): {_summary(embedded)}")
        distributed = latency(files, root / "dist", {"data_dir": str(root / "dist-data"), "queue_name": "lat",
                                                    **queue}, args.latency_jobs)
        print(f"  distributed (Redis + RQ + svrnet-worker): {_summary(distributed)}")
        print(f"  added by the queue: median {statistics.median(distributed) - statistics.median(embedded):+.1f} ms, "
              f"p90 {_p90(distributed) - _p90(embedded):+.1f} ms")
        cluster(files, root / "cluster", {"data_dir": str(root / "cluster-data"),
                                          "queue_name": f"c{uuid.uuid4().hex[:8]}", **queue}, args.jobs)
    finally:
        server.stop()
        scratch.cleanup()


if __name__ == "__main__":
    main()
