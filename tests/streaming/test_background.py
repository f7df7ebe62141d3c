"""The streams' stage process ends with the server: a server stopped (SIGTERM runs the app's lifespan
to its end) leaves no process behind, where ``shutdown(wait=False)`` alone left it running."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

from fastapi.testclient import TestClient

from service.core.settings import Settings
from service.inference.registry import ModelRegistry
from service.main import create_app
from service.core.threads import blas_threads
from service.streaming.background import STAGE_BLAS_THREADS, run_in_stage_process, stage_process, stop_stage_process
from tests.api.conftest import OracleEstimator
from tests.support.live_server import gone_within
from tests.support.scratch import job_store_dir


def _worker():  # noqa: ANN202 - the pool's one process, started by a first task
    pool = stage_process()
    assert pool.submit(int).result() == 0
    return next(iter(pool._processes.values()))


def test_the_stage_process_ends_and_a_new_one_starts_on_next_use() -> None:
    first = _worker()
    stop_stage_process()
    assert not first.is_alive()
    second = _worker()
    assert second.pid != first.pid and second.is_alive()
    stop_stage_process()
    assert not second.is_alive()
    stop_stage_process()                                                # nothing started: nothing to do


def test_a_fit_still_running_at_the_stop_is_ended_with_its_process() -> None:
    worker = _worker()
    running = stage_process().submit(time.sleep, 60)
    while not running.running():
        time.sleep(0.01)
    stop_stage_process(timeout_s=0.5)
    assert not worker.is_alive()


def test_a_stage_process_that_died_is_replaced_and_the_fit_run_in_the_new_one() -> None:
    worker = _worker()
    worker.kill()                                                       # the OS's memory killer, a crash
    worker.join(5)
    assert run_in_stage_process(pow, 2, 10) == 1024
    assert run_in_stage_process(pow, 3, 2) == 9                         # and every fit after it
    assert next(iter(stage_process()._processes.values())).pid != worker.pid
    stop_stage_process()


def test_the_stage_process_runs_one_blas_thread() -> None:
    stop_stage_process()
    assert set(stage_process().submit(blas_threads).result()) == {STAGE_BLAS_THREADS}
    stop_stage_process()


def test_firm_ups_that_start_at_once_share_one_stage_process() -> None:
    stop_stage_process()
    barrier = threading.Barrier(8)

    def first_use() -> ProcessPoolExecutor:
        barrier.wait()
        return stage_process()

    with ThreadPoolExecutor(8) as threads:
        pools = list(threads.map(lambda _: first_use(), range(8)))
    assert all(pool is pools[0] for pool in pools)                     # one process, which a stop ends
    worker = _worker()
    stop_stage_process()
    assert not worker.is_alive()


def test_the_server_s_lifespan_ends_the_stage_process() -> None:
    app = create_app(Settings(data_dir=job_store_dir()),
                     registry=ModelRegistry({"default": OracleEstimator()}))
    with TestClient(app):
        worker = _worker()                                               # a stream's firm-up started it
        assert worker.is_alive()
    assert not worker.is_alive()


def test_the_stage_process_ends_with_a_server_killed_at_once(tmp_path) -> None:  # noqa: ANN001
    """``kill -9`` of the process that started the stage process (no lifespan runs): the stage
    process sees its parent gone and ends, rather than holding its memory for ever."""
    import os
    import signal
    import subprocess
    import sys

    script = ("import os, time\n"
              "from service.streaming.background import stage_process\n"
              "print(stage_process().submit(os.getpid).result(), flush=True)\n"
              "time.sleep(60)\n")
    server = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=tmp_path,
                              env={**os.environ, "PYTHONPATH": os.getcwd()})
    try:
        child = int(server.stdout.readline())
        os.kill(child, 0)                                                  # running
        server.send_signal(signal.SIGKILL)
        server.wait(10)
        assert gone_within(child, 10.0), "the stage process outlived the server"
    finally:
        server.kill()
