"""What is refused before an upload is read (``deps.early_rejection``): a job submission's
``Idempotency-Key`` lets it past a full queue only where the key already made a job."""

from __future__ import annotations

from types import SimpleNamespace

from service.api.deps import early_rejection, idempotency_digest
from service.core.errors import InvalidParameter, QueueFull
from service.core.settings import Settings


class FullQueue:
    """A job store whose queue holds its maximum, and one job made under a known key."""

    def __init__(self, keys: set[str]) -> None:
        self.keys = keys

    def queued(self) -> list[object]:
        return [object()]

    def job_for_key(self, digest: str) -> object | None:
        return object() if digest in self.keys else None


def test_a_full_queue_refuses_new_submissions_keyed_or_not_before_their_upload() -> None:
    known = "k-retry-of-a-lost-answer"
    state = SimpleNamespace(settings=Settings(max_queued_jobs=1), job_store=FullQueue({idempotency_digest(known)}))
    submit = lambda headers: early_rejection(state, "POST", "/v1/reconstructions", headers)  # noqa: E731
    assert isinstance(submit({}), QueueFull)
    assert isinstance(submit({"idempotency-key": "k-a-new-submission"}), QueueFull)    # any key skipped it before
    assert isinstance(submit({"idempotency-key": "x"}), InvalidParameter)              # no key at all: said at once
    assert submit({"idempotency-key": known}) is None          # a retry: the route answers with its key's job


def test_the_liveness_probe_is_answered_while_every_worker_thread_is_taken() -> None:
    """``/healthz`` needs no thread of the app's pool: its one dependency (the query check) runs on the
    event loop, as do the API key's and the app state's of every route (``/v1/models`` here). Status reads of a job store that stalls (a Redis that stopped answering) can take
    every thread; the replica is then unready, but never taken for dead and restarted."""
    import threading

    from anyio import to_thread

    from service.inference.registry import ModelRegistry
    from tests.api.conftest import OracleEstimator, make_client

    taken, released = threading.Event(), threading.Event()

    def occupy() -> bool:
        taken.set()
        return released.wait(10)            # False: nothing else was answered meanwhile

    async def take_every_thread() -> bool:
        to_thread.current_default_thread_limiter().total_tokens = 1
        return await to_thread.run_sync(occupy)

    with make_client(ModelRegistry({"default": OracleEstimator()}), api_keys="k1") as client:
        holding = client.portal.start_task_soon(take_every_thread)
        assert taken.wait(10)
        r = client.get("/healthz")
        models = client.get("/v1/models", headers={"X-API-Key": "k1"})   # the key, the registry: no thread either
        refused = client.get("/v1/models")
        released.set()
        assert holding.result(10) is True and r.status_code == 200
        assert models.status_code == 200 and refused.status_code == 401
        assert client.get("/healthz?x=1").status_code == 400          # the query check still runs


def test_an_idle_server_hands_its_heap_back_once_the_last_request_s_processing_has_ended(
        monkeypatch: object, phantom_files: tuple) -> None:
    """A request's stages leave freed pages in the threads' heaps: the server trims them a moment after
    its last processing ends, and not while a request is processing."""
    import threading
    import time

    from service.api import deps
    from service.inference.registry import ModelRegistry
    from tests.api.conftest import OracleEstimator, make_client

    trimmed = threading.Event()
    monkeypatch.setattr(deps, "TRIM_AFTER_S", 0.05)
    monkeypatch.setattr(deps, "trim_heap", trimmed.set)
    stack, _, _ = phantom_files
    with make_client(ModelRegistry({"default": OracleEstimator()})) as client:
        state = client.app.state
        state.processing_now = 1                       # a request still processing: no trim
        deps._trim_if_idle(state)
        time.sleep(0.2)
        assert not trimmed.is_set()
        state.processing_now = 0
        r = client.post("/v1/masks", files=[("stacks", ("s.nii.gz", stack.read_bytes()))])
        assert r.status_code == 200, r.text
        assert trimmed.wait(5)
