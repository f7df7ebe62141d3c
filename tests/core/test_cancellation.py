"""A request's cancellation reaches the threads its stages run in: anyio's worker threads (the
API's ``to_thread.run_sync``) and the pools a stage fans out to (:func:`carried`)."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import anyio
import pytest
from anyio import to_thread

from service.core.cancellation import cancelled_by, carried, checkpoint
from service.core.errors import ClientGone


def test_a_stage_in_an_anyio_worker_thread_sees_its_requests_event() -> None:
    async def request() -> None:
        with cancelled_by(threading.Event()) as gone:
            await to_thread.run_sync(checkpoint)          # the client is still there: no error
            gone.set()
            with pytest.raises(ClientGone):
                await to_thread.run_sync(checkpoint)

    anyio.run(request)


def test_one_carried_function_runs_in_many_pool_threads_at_once_and_outside_a_request() -> None:
    barrier = threading.Barrier(3)

    def step(_: int) -> None:
        barrier.wait(5)                                   # three at once in the same carried function
        checkpoint()

    with cancelled_by(threading.Event()) as gone:
        work = carried(step)
        with ThreadPoolExecutor(3) as pool:
            assert list(pool.map(work, range(3))) == [None] * 3
            gone.set()
            barrier.reset()
            futures = [pool.submit(work, i) for i in range(3)]
            failures = [f.exception(10) for f in futures]
    assert all(isinstance(f, ClientGone) for f in failures)
    carried(checkpoint)()                                 # made outside a request: nothing to stop
