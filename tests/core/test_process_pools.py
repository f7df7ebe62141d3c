"""Ending a process pool: work past its grace is terminated, queued work cancelled, no process left."""

from __future__ import annotations

import multiprocessing
import os
import signal
import time
from concurrent.futures import ProcessPoolExecutor


from service.core.process_pools import end_pool, ignore_interrupts, watch_parent
from tests.support.live_server import gone_within


def _pid_after(seconds: float) -> int:
    time.sleep(seconds)
    return os.getpid()


def test_work_past_its_grace_is_ended_and_queued_work_cancelled() -> None:
    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
    running = pool.submit(_pid_after, 60.0)
    queued = [pool.submit(_pid_after, 60.0) for _ in range(3)]
    time.sleep(1.0)                                               # the first has started in the worker
    t0 = time.monotonic()
    workers = end_pool(pool, grace_s=0.5, timeout_s=5.0)
    assert time.monotonic() - t0 < 15.0                          # not the minute the work asked for
    assert workers and not any(w.is_alive() for w in workers)
    for future in [running, *queued]:                              # none of it finished: cancelled or broken
        assert future.done()
        if not future.cancelled():
            assert isinstance(future.exception(timeout=0), Exception)
    assert sum(q.cancelled() for q in queued) >= 2                  # what had not reached a worker's queue


def test_work_within_its_grace_finishes() -> None:
    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
    done = pool.submit(_pid_after, 0.2)
    pid = done.result(timeout=60.0)                                # the worker is up
    again = pool.submit(_pid_after, 0.3)
    deadline = time.monotonic() + 10.0
    while not again.running() and time.monotonic() < deadline:   # handed to the worker: no longer cancellable
        time.sleep(0.01)
    workers = end_pool(pool, grace_s=10.0)
    assert again.result(timeout=1.0) == pid and not any(w.is_alive() for w in workers)


def _orphan(ready: multiprocessing.Queue) -> None:  # noqa: ANN001
    grandchild = multiprocessing.get_context("spawn").Process(target=_watching, args=(os.getpid(),))
    grandchild.start()
    ready.put(grandchild.pid)
    ready.close()
    ready.join_thread()                                             # the pid sent before the exit below
    os._exit(0)                                                     # the parent gone, as after a kill -9


def _watching(parent: int) -> None:
    watch_parent(parent, interval_s=0.05)                          # its starter's pid, passed by it
    time.sleep(60.0)


def test_a_pool_process_exits_when_its_parent_is_gone() -> None:
    ctx = multiprocessing.get_context("spawn")
    ready = ctx.Queue()
    parent = ctx.Process(target=_orphan, args=(ready,))
    parent.start()
    grandchild = ready.get(timeout=60.0)
    parent.join(30.0)
    assert gone_within(grandchild, 20.0), "the pool process outlived its parent by 20 s"


def test_a_ctrl_c_leaves_an_idle_pool_process_to_its_owner(capfd) -> None:  # noqa: ANN001
    """Its SIGINT ignored, a pool process interrupted waiting for work neither dies nor prints the
    wait's traceback; the owner ends it."""
    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=ignore_interrupts)
    pid = pool.submit(os.getpid).result(timeout=60.0)
    os.kill(pid, signal.SIGINT)
    time.sleep(0.5)
    assert pool.submit(os.getpid).result(timeout=10.0) == pid        # still there, still working
    workers = end_pool(pool, grace_s=1.0)
    assert not any(w.is_alive() for w in workers)
    assert "KeyboardInterrupt" not in capfd.readouterr().err
