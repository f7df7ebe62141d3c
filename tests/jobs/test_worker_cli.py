"""``svrnet-worker --workers N``: the pool's signal handling, with the worker body replaced by one that
mimics RQ's start-up window (registered, handlers not yet installed) so the race is hit every time."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

pytest.importorskip("rq", reason="svrnet-worker needs the queue extra (rq, redis)")

ROOT = Path(__file__).resolve().parents[2]

@contextmanager
def pool_process(script: str, folder: Path) -> Iterator[subprocess.Popen]:
    """``script`` run with ``folder`` as its argument, in a session of its own that is killed whole after."""
    proc = subprocess.Popen([sys.executable, "-c", script, str(folder)], cwd=ROOT, start_new_session=True)
    try:
        yield proc
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def wait_for_workers(proc: subprocess.Popen, folder: Path, n: int) -> None:
    """Until ``n`` workers have started (each leaves a file in ``folder``), the pool still running."""
    deadline = time.time() + 30
    while len(list(folder.iterdir())) < n:
        assert time.time() < deadline and proc.poll() is None
        time.sleep(0.02)


POOL = textwrap.dedent("""
    import os, sys, time
    from pathlib import Path
    from service.jobs import worker_cli

    ready = Path(sys.argv[1])

    def rq_like_work(settings, burst=False, name=None):
        # As worker_cli.work: hold the stop signals, then (RQ) register and only later install handlers.
        worker_cli.hold_stop_signals()
        (ready / str(os.getpid())).touch()                    # "registered"
        time.sleep(2.0)                                        # the window before RQ's handlers
        sys.exit(0 if worker_cli._early_stops else 3)          # 3: the stop request never arrived

    worker_cli.work = rq_like_work
    sys.exit(worker_cli._pool(None, 2, False))
""")


def test_a_stop_signal_in_a_workers_start_up_window_is_a_warm_stop_not_a_kill(tmp_path: Path) -> None:
    # Each pooled worker runs a parent-watch thread (and BLAS pools); a SIGTERM forwarded before RQ has
    # installed its handlers must not land on such a thread and kill the worker with -15.
    with pool_process(POOL, tmp_path) as proc:
        wait_for_workers(proc, tmp_path, 2)
        os.kill(proc.pid, signal.SIGTERM)
        assert proc.wait(timeout=30) == 0                    # both workers saw the stop, neither was killed



EARLY_STOP = textwrap.dedent("""
    import os, signal
    from service.core.settings import Settings
    from service.jobs import worker_cli

    # a SIGTERM that arrives while the worker starts, before RQ's handlers are in place
    worker_cli.hold_stop_signals()
    os.kill(os.getpid(), signal.SIGTERM)
    worker_cli.work(Settings())
    print("returned")
""")


def test_a_stop_signal_during_start_up_unregisters_and_exits_cleanly(tmp_path: Path, redis_url: str) -> None:
    import redis
    from rq import Queue
    from rq.worker import Worker as RqWorker

    name = f"t{os.getpid()}early"
    env = {**os.environ, "SVRNET_QUEUE_URL": redis_url, "SVRNET_QUEUE_NAME": name, "SVRNET_DATA_DIR": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", EARLY_STOP], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=60)
    # RQ's own handler would raise StopRequested outside its loop: exit 1 and a stale registration
    assert done.returncode == 0 and "returned" in done.stdout, done.stderr[-2000:]
    queue = Queue(name, connection=redis.Redis.from_url(redis_url))
    assert RqWorker.count(queue=queue) == 0


def test_a_worker_logs_only_json_lines_on_stderr_rq_s_own_included(tmp_path: Path, redis_url: str) -> None:
    """A log shipper reads one stream of JSON lines: RQ's own lines (its start, its registries, its
    end) come as the service's do, on stderr, nothing on stdout."""
    import json

    env = {**os.environ, "SVRNET_QUEUE_URL": redis_url, "SVRNET_QUEUE_NAME": f"t{os.getpid()}json",
           "SVRNET_DATA_DIR": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", "from service.jobs.worker_cli import run; run()", "--burst"],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    lines = [json.loads(line) for line in done.stderr.splitlines()]
    assert done.stdout == "" and any(line["logger"].startswith("rq.") for line in lines), done.stderr


def test_a_worker_whose_queue_does_not_answer_says_so_in_one_json_line(tmp_path: Path) -> None:
    """Redis not there at the start (nothing listens on the port): the worker exits 1 with one JSON
    line saying why (its kind and place), and ``--health`` exits 1 with one line, no traceback
    (a log shipper got 60 lines of traceback, a health check's output the same)."""
    import json
    import socket

    with socket.socket() as free:
        free.bind(("127.0.0.1", 0))
        port = free.getsockname()[1]
    env = {**os.environ, "SVRNET_QUEUE_URL": f"redis://127.0.0.1:{port}/0", "SVRNET_QUEUE_NAME": "tnone",
           "SVRNET_DATA_DIR": str(tmp_path)}
    command = [sys.executable, "-c", "from service.jobs.worker_cli import run; run()"]
    done = subprocess.run([*command, "--burst"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
    lines = [json.loads(line) for line in done.stderr.splitlines()]
    assert done.returncode == 1 and lines[-1]["error_type"] == "ConnectionError", done.stderr[-2000:]
    assert "Traceback" not in done.stderr
    health = subprocess.run([*command, "--health"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
    assert health.returncode == 1 and "Traceback" not in health.stderr and len(health.stderr.splitlines()) == 1


def test_rq_s_lines_are_cut_to_their_first_line_on_every_rq_logger() -> None:
    """RQ appends a failed job's traceback (whose text may name a client's file) to the line of its
    ``rq.worker`` logger: only the first line reaches the log."""
    import json

    script = textwrap.dedent("""
        import logging
        from service.core import logging as service_logging
        service_logging.configure("info", libraries=("rq",))
        logging.getLogger("rq.worker").error("job %s: exception raised (%s)\\n%s", "j1", "f",
                                             "Traceback ...\\nUnusableImage: jane_doe.nii.gz")
    """)
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=60)
    (line,) = [json.loads(x) for x in done.stderr.splitlines()]
    assert line["msg"] == "job j1: exception raised (f)" and "jane" not in done.stderr, done.stderr


RESTARTING_POOL = textwrap.dedent("""
    import os, sys, time
    from pathlib import Path
    from service.jobs import worker_cli

    started = Path(sys.argv[1])
    worker_cli.RESTART_DELAY_S = 0.1

    def crashing_then_steady_work(settings, burst=False, name=None):
        # The first two workers end at once, unasked (as RQ quits when Redis goes away while a job
        # runs); the ones started in their place work until the pool forwards a stop.
        worker_cli.hold_stop_signals()
        (started / str(os.getpid())).touch()
        if len(list(started.iterdir())) <= 2:
            sys.exit(1)
        while not worker_cli._early_stops:
            time.sleep(0.05)
        sys.exit(0)

    worker_cli.work = crashing_then_steady_work
    sys.exit(worker_cli._pool(None, 2, False))
""")


def test_a_worker_that_ends_unasked_is_started_again_and_the_pool_still_stops_warm(tmp_path: Path) -> None:
    with pool_process(RESTARTING_POOL, tmp_path) as proc:
        wait_for_workers(proc, tmp_path, 4)                      # two ended, two started in their place
        time.sleep(0.3)
        assert proc.poll() is None and len(list(tmp_path.iterdir())) == 4   # the pool keeps two, no more
        os.kill(proc.pid, signal.SIGTERM)
        assert proc.wait(timeout=30) == 0


@pytest.mark.parametrize("lost_after_s", [5, 60])
def test_an_idle_workers_health_holds_between_its_beats_whatever_the_lost_after_setting(
        lost_after_s: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """An idle RQ worker beats only when its wait for a job ends (its registration's life less 15 s):
    ``--health`` counts it alive for that life and a heartbeat interval, at least 30 s, so that a small
    ``SVRNET_WORKER_LOST_AFTER_S`` does not make a container's health check flap; a worker silent past
    it is not alive."""
    import socket
    from datetime import datetime, timedelta, timezone
    from types import SimpleNamespace

    from service.core.settings import Settings
    from service.jobs import worker_cli

    settings = Settings(queue_url="redis://127.0.0.1:1/0", worker_heartbeat_s=2, worker_lost_after_s=lost_after_s)
    life = worker_cli.worker_ttl_s(settings)
    assert life == max(30, lost_after_s)
    beats: list[float] = []
    monkeypatch.setattr(worker_cli.redis.Redis, "from_url", staticmethod(lambda *a, **k: None))
    monkeypatch.setattr(worker_cli, "Queue", lambda *a, **k: None)
    monkeypatch.setattr(worker_cli.Worker, "all", staticmethod(lambda **k: [SimpleNamespace(
        hostname=socket.gethostname(), last_heartbeat=datetime.now(timezone.utc) - timedelta(seconds=beats[-1]))]))
    for silent_s, alive in ((life - 15 + 1, True), (life + 1, True), (life + settings.worker_heartbeat_s + 5, False)):
        beats.append(silent_s)
        assert worker_cli.healthy(settings) is alive, silent_s
