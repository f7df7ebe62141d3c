"""``svrnet-worker --workers N``: the pool's signal handling, with the worker body replaced by one that
mimics RQ's start-up window (registered, handlers not yet installed) so the race is hit every time."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

pytest.importorskip("rq", reason="svrnet-worker needs the queue extra (rq, redis)")

ROOT = Path(__file__).resolve().parents[2]

POOL = textwrap.dedent("""
    import signal, sys, time
    from pathlib import Path
    from service.jobs import worker_cli

    ready = Path(sys.argv[1])

    def rq_like_work(settings, burst=False, name=None):
        # As worker_cli.work: block the stop signals, then (RQ) register and only later install handlers.
        signal.pthread_sigmask(signal.SIG_BLOCK, worker_cli.STOP_SIGNALS)
        (ready / str(__import__("os").getpid())).touch()      # "registered"
        time.sleep(2.0)                                        # the window before RQ's handlers
        stopped = []
        signal.signal(signal.SIGTERM, lambda *a: stopped.append(1))
        signal.pthread_sigmask(signal.SIG_UNBLOCK, worker_cli.STOP_SIGNALS)
        time.sleep(0.3)
        sys.exit(0 if stopped else 3)                          # 3: the stop request never arrived

    worker_cli.work = rq_like_work
    sys.exit(worker_cli._pool(None, 2, False))
""")


def test_a_stop_signal_in_a_workers_start_up_window_is_a_warm_stop_not_a_kill(tmp_path: Path) -> None:
    # Each pooled worker runs a parent-watch thread; a SIGTERM forwarded while RQ had not yet installed
    # its handlers used to land on that thread (which did not block it) and kill the worker with -15.
    proc = subprocess.Popen([sys.executable, "-c", POOL, str(tmp_path)], cwd=ROOT, start_new_session=True)
    try:
        deadline = time.time() + 30
        while len(list(tmp_path.iterdir())) < 2:
            assert time.time() < deadline and proc.poll() is None
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGTERM)
        assert proc.wait(timeout=30) == 0                    # both workers saw the stop, neither was killed
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass

