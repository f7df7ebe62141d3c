"""Admission and processing slots: reconstructions, masks and predictions are admitted before their
upload is read (503 with Retry-After when every admission is taken) and take a processing slot once
their upload is in (waited for, then 503), so a slow upload holds no processing; uploads decode within
bounded memory however many clients send at once: at most ``READ_WORKERS`` files are decoded at a
time in the whole process."""

from __future__ import annotations

import asyncio
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from service.api import uploads
from service.inference.estimator import OnnxPoseEstimator
from service.inference.model_file import load_model
from service.inference.registry import ModelRegistry
from tests.support import corpus
from tests.api.conftest import make_client
from tests.api.test_operations import _call_without_reading_the_body


@pytest.mark.parametrize("route", ["/v1/reconstructions", "/v1/masks", "/v1/predict"])
def test_a_server_with_every_admission_taken_refuses_uploads_before_reading_them(oracle, route: str) -> None:  # noqa: ANN001
    with make_client(ModelRegistry({"default": oracle}), max_concurrent=1, retry_after_s=4) as client:
        client.app.state.admissions._value = 0
        status, headers, read = _call_without_reading_the_body(client.app, route, [])
        assert (status, read, headers["retry-after"]) == (503, False, "4")
        r = client.post(route, files=[("stacks", ("s.nii.gz", b"x"))])
        assert r.status_code == 503 and r.headers["retry-after"] == "4"


def _scope(app, path: str = "/v1/predict", content_type: bytes = b"multipart/form-data; boundary=xx") -> dict:  # noqa: ANN001
    return {"type": "http", "method": "POST", "path": path, "raw_path": path.encode(), "query_string": b"",
            "headers": [(b"content-type", content_type)], "app": app, "root_path": "", "scheme": "http",
            "server": ("test", 80), "client": ("test", 1)}


def _sender(answers: dict, name: str):  # noqa: ANN202
    async def send(message: dict) -> None:
        if message["type"] == "http.response.start":
            answers[name] = (message["status"], {k.decode(): v.decode() for k, v in message["headers"]})
    return send


def test_requests_that_arrive_together_beyond_the_admissions_are_refused_before_their_uploads(oracle) -> None:  # noqa: ANN001
    """One admission, two uploads at the same moment: the second is refused (503) while the first is
    still uploading, its body unread; the first's admission is free again once it has its answer."""
    with make_client(ModelRegistry({"default": oracle}), max_concurrent=1, max_admitted=1, retry_after_s=3) as client:
        app, answers, read = client.app, {}, {"second": False}

        async def scenario() -> None:
            uploading, finish = asyncio.Event(), asyncio.Event()

            async def slow() -> dict:                      # the first client's body, still on its way
                uploading.set()
                await finish.wait()
                return {"type": "http.request", "body": b"x" * 1000, "more_body": False}

            async def quick() -> dict:
                read["second"] = True
                return {"type": "http.request", "body": b"x" * 1000, "more_body": False}

            first = asyncio.create_task(app(_scope(app), slow, _sender(answers, "first")))
            await uploading.wait()
            await app(_scope(app), quick, _sender(answers, "second"))
            finish.set()
            await first

        asyncio.run(scenario())
        status, headers = answers["second"]
        assert (status, read["second"], headers["retry-after"]) == (503, False, "3")
        assert answers["first"][0] == 400                  # its garbage body, read and refused: not a 503
        assert app.state.admissions._value == 1 and app.state.slots._value == 1      # given back


def test_a_slow_upload_holds_no_processing_slot(tiny_model_path: Path, phantom_files) -> None:  # noqa: ANN001
    """One processing slot; a client's upload trickles in and is not whole yet: a quicker client's
    request is processed meanwhile (200), not refused because the slow one holds the slot."""
    registry = ModelRegistry({"default": OnnxPoseEstimator(load_model(tiny_model_path))})
    stack, mask, _ = phantom_files
    with make_client(registry, max_concurrent=1, max_admitted=2) as client:
        app, answers = client.app, {}
        uploading, finish = threading.Event(), asyncio.Event()

        async def slow() -> dict:
            uploading.set()
            await finish.wait()
            return {"type": "http.request", "body": b"x" * 1000, "more_body": False}

        async def wake() -> None:
            finish.set()

        first = client.portal.start_task_soon(app, _scope(app), slow, _sender(answers, "first"))
        assert uploading.wait(10)
        r = client.post("/v1/predict", files=[("stacks", (stack.name, stack.read_bytes())),
                                              ("masks", (mask.name, mask.read_bytes()))], data={"mc_samples": "2"})
        assert r.status_code == 200, r.text
        client.portal.call(wake)
        first.result(10)
        assert answers["first"][0] == 400
        assert app.state.admissions._value == 2 and app.state.slots._value == 1


def test_a_request_whose_upload_is_in_waits_for_a_slot_then_is_refused(oracle, phantom_files) -> None:  # noqa: ANN001
    """Every processing slot taken: a valid request's upload is read, and it waits ``slot_wait_s`` for
    a slot; a slot given back meanwhile serves it, none given back is a 503 with Retry-After. An
    invalid request gets its 400 at once, busy or not; ``slot_wait_s=0`` refuses at once when busy and
    serves at once when free."""
    stack, _, _ = phantom_files
    files = [("stacks", (stack.name, stack.read_bytes()))]
    with make_client(ModelRegistry({"default": oracle}), max_concurrent=1, slot_wait_s=0.3, retry_after_s=6) as client:
        client.app.state.slots._value = 0
        started = time.perf_counter()
        r = client.post("/v1/predict", files=files, data={"bias_correction": "false"})
        assert r.status_code == 503 and r.headers["retry-after"] == "6" and "waited" in r.json()["detail"]
        assert time.perf_counter() - started >= 0.3
    with make_client(ModelRegistry({"default": oracle}), max_concurrent=1, slot_wait_s=30) as client:
        client.app.state.slots._value = 0
        started = time.perf_counter()
        r = client.post("/v1/predict", files=files, data={"variance_threshold": "x"})
        assert r.status_code == 400 and "variance_threshold" in r.text
        assert time.perf_counter() - started < 10                         # not after the 30 s wait for a slot

        async def give_back() -> None:
            await asyncio.sleep(0.3)
            client.app.state.slots.release()

        client.portal.start_task_soon(give_back)
        oracle.truth = np.repeat(np.eye(4)[None], 16, 0)
        r = client.post("/v1/predict", files=files, data={"stack_consistency": "false", "mc_samples": "2"})
        assert r.status_code == 200, r.text                                  # served once the slot came back
    with make_client(ModelRegistry({"default": oracle}), max_concurrent=1, slot_wait_s=0) as client:
        r = client.post("/v1/predict", files=files, data={"stack_consistency": "false", "mc_samples": "2"})
        assert r.status_code == 200, r.text                                  # free: served at once
        client.app.state.slots._value = 0
        assert client.post("/v1/predict", files=files).status_code == 503    # busy: refused at once


def test_the_slot_is_free_again_before_the_answer_is_sent(oracle, phantom_files) -> None:  # noqa: ANN001
    """A client that reads its answer slowly holds no processing slot: it is given back when the work
    ends, before the answer's first byte."""
    import httpx

    stack, _, _ = phantom_files
    built = httpx.Request("POST", "http://test/v1/predict", data={"stack_consistency": "false", "mc_samples": "2"},
                          files=[("stacks", (stack.name, stack.read_bytes()))])
    body, content_type = built.read(), built.headers["content-type"].encode()
    oracle.truth = np.repeat(np.eye(4)[None], 16, 0)
    with make_client(ModelRegistry({"default": oracle}), max_concurrent=1) as client:
        app, free_when_answered, sent = client.app, [], [False]

        async def scenario() -> None:
            async def receive() -> dict:
                if not sent[0]:
                    sent[0] = True
                    return {"type": "http.request", "body": body, "more_body": False}
                await asyncio.sleep(3600)                    # the client neither sends nor leaves

            async def send(message: dict) -> None:
                if message["type"] == "http.response.start":
                    free_when_answered.append((message["status"], app.state.slots._value))

            await asyncio.wait_for(app(_scope(app, content_type=content_type), receive, send), 30)

        client.portal.call(scenario)
    assert free_when_answered == [(200, 1)]


def test_a_client_that_leaves_while_its_request_waits_for_a_slot_takes_none(oracle, phantom_files) -> None:  # noqa: ANN001
    import httpx

    stack, _, _ = phantom_files
    built = httpx.Request("POST", "http://test/v1/predict", files=[("stacks", (stack.name, stack.read_bytes()))])
    body, content_type = built.read(), built.headers["content-type"].encode()
    with make_client(ModelRegistry({"default": oracle}), max_concurrent=1, max_admitted=2, slot_wait_s=30) as client:
        app, answers, sent = client.app, {}, [False]
        app.state.slots._value = 0                               # the one slot busy elsewhere

        async def scenario() -> None:
            async def receive() -> dict:
                if not sent[0]:
                    sent[0] = True
                    return {"type": "http.request", "body": body, "more_body": False}
                await asyncio.sleep(0.2)                         # then the client gives up
                return {"type": "http.disconnect"}

            await asyncio.wait_for(app(_scope(app, content_type=content_type), receive, _sender(answers, "gone")), 10)

        started = time.perf_counter()
        client.portal.call(scenario)
        assert time.perf_counter() - started < 5                # not the 30 s of the wait
        assert answers["gone"][0] == 499
        assert app.state.slots._value == 0 and app.state.admissions._value == 2
        app.state.slots.release()                                # the slot taken elsewhere comes back:
        assert app.state.slots._value == 1                       # none was taken by the request that left


def test_no_more_than_two_files_decode_at_once_across_requests(monkeypatch: pytest.MonkeyPatch,
                                                                tmp_path: Path) -> None:
    busy, peak, lock = [0], [0], threading.Lock()
    real = uploads.read_upload

    def tracked(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        with lock:
            busy[0] += 1
            peak[0] = max(peak[0], busy[0])
        time.sleep(0.05)
        try:
            return real(*args, **kwargs)
        finally:
            with lock:
                busy[0] -= 1

    monkeypatch.setattr(uploads, "read_upload", tracked)

    class Upload:
        def __init__(self, data: bytes, name: str) -> None:
            import io

            self.file, self.filename, self.size = io.BytesIO(data), name, len(data)

    data = corpus.gz(corpus.nifti(np.ones((6, 6, 4))))

    def request(i: int) -> int:
        folder = tmp_path / f"r{i}"
        folder.mkdir()
        return len(uploads.save_and_read([Upload(data, f"s{j}.nii.gz") for j in range(4)], [], folder))

    with ThreadPoolExecutor(6) as pool:
        assert list(pool.map(request, range(6))) == [4] * 6
    assert peak[0] == uploads.READ_WORKERS


def test_a_request_whose_first_file_fails_does_not_read_the_rest(monkeypatch: pytest.MonkeyPatch,
                                                                  tmp_path: Path) -> None:
    import io

    from service.core.errors import UnsupportedFile

    read: list[str] = []
    real = uploads.read_upload

    def tracked(path, name, **kwargs):  # noqa: ANN001, ANN003, ANN202
        read.append(name)
        time.sleep(0.05)
        return real(path, name, **kwargs)

    monkeypatch.setattr(uploads, "read_upload", tracked)

    class Upload:
        def __init__(self, data: bytes, name: str) -> None:
            self.file, self.filename, self.size = io.BytesIO(data), name, len(data)

    good = corpus.gz(corpus.nifti(np.ones((6, 6, 4))))
    files = [Upload(b"not an image", "bad.nii.gz")] + [Upload(good, f"s{j}.nii.gz") for j in range(8)]
    with pytest.raises(UnsupportedFile, match="bad.nii.gz"):
        uploads.save_and_read(files, [], tmp_path)
    assert len(read) <= uploads.READ_WORKERS + 1, read          # those under way finish; no more start


def test_each_uploads_spooled_copy_is_deleted_once_it_is_written_to_the_request_folder(tmp_path: Path) -> None:
    """The form parser spools every file of a request to disk before the route runs; each spool goes
    as soon as its file is in the request's folder, so a request holds its files on disk once."""
    import tempfile

    class Upload:
        def __init__(self, data: bytes, name: str) -> None:
            self.file = tempfile.SpooledTemporaryFile(max_size=0, dir=tmp_path)    # on disk at once
            self.file.write(data)
            self.filename, self.size = name, len(data)

    data = corpus.gz(corpus.nifti(np.ones((6, 6, 4))))
    files = [Upload(data, f"s{j}.nii.gz") for j in range(3)]
    folder = tmp_path / "request"
    folder.mkdir()
    assert not any(f.file.closed for f in files)
    assert len(uploads.save_and_read(files, [], folder)) == 3
    assert all(f.file.closed for f in files)          # an unnamed temporary file: closed is deleted


def _leaving_client(app, phantom_files, leave: threading.Event, path: str = "/v1/predict") -> tuple:  # noqa: ANN001
    """Send ``path`` the phantom with its mask in one piece, then close the connection once
    ``leave`` is set: the scenario to run on the app's portal, and the answers it sends
    (``answers["gone"]``: status, headers)."""
    import httpx

    stack, mask, _ = phantom_files
    built = httpx.Request("POST", f"http://test{path}", data={"mc_samples": "2"},
                          files=[("stacks", (stack.name, stack.read_bytes())), ("masks", (mask.name, mask.read_bytes()))])
    body, content_type = built.read(), built.headers["content-type"].encode()
    answers, sent = {}, [False]

    async def receive() -> dict:
        if not sent[0]:
            sent[0] = True
            return {"type": "http.request", "body": body, "more_body": False}
        while not leave.is_set():
            await asyncio.sleep(0.01)
        return {"type": "http.disconnect"}

    async def scenario() -> None:
        await asyncio.wait_for(app(_scope(app, path, content_type), receive, _sender(answers, "gone")), 30)

    return scenario, answers


def _predicts_counted(client) -> list[str]:  # noqa: ANN001
    """The ``svrnet_requests_total`` lines of ``/v1/predict`` the app's metrics hold."""
    return [line for line in client.get("/metrics").text.splitlines()
            if line.startswith("svrnet_requests_total{") and 'route="/v1/predict"' in line]


def test_a_request_whose_client_leaves_stops_at_its_next_step_and_frees_its_slot(
        oracle, phantom_files, monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: ANN001
    """The client closes its connection while its stacks are prepared: the work stops at the next step
    (the network never runs), the slot and the admission are free again, and the request is
    recorded as 499 (no one got an answer)."""
    from service.api import predict as route
    from service.core import cancellation

    preparing, steps = threading.Event(), []
    real_prepare, real_predict = route.prepare_stacks, route.run_prediction

    def prepare(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        steps.append("prepare")
        preparing.set()
        assert cancellation._GONE.get().wait(10), "the request never learnt that its client left"
        return real_prepare(*args, **kwargs)

    def predict(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        steps.append("predict")
        return real_predict(*args, **kwargs)

    monkeypatch.setattr(route, "prepare_stacks", prepare)
    monkeypatch.setattr(route, "run_prediction", predict)
    with make_client(ModelRegistry({"default": oracle}), max_concurrent=1, max_admitted=2) as client:
        scenario, _ = _leaving_client(client.app, phantom_files, preparing)   # it leaves as its stacks are prepared
        client.portal.call(scenario)
        assert steps == ["prepare"]                          # stopped before the network
        assert client.app.state.slots._value == 1 and client.app.state.admissions._value == 2
        counted = _predicts_counted(client)
    assert len(counted) == 1 and 'status="499"' in counted[0], counted


def test_a_client_that_leaves_during_the_last_step_is_counted_as_gone_not_answered(
        oracle, phantom_files, monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: ANN001
    """The client closes its connection while the poses are made, past the last checkpoint: the work
    ends, and the request is recorded as 499, not as a 200 no one received."""
    from service.api import predict as route
    from service.core import cancellation

    predicting = threading.Event()

    def predict(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        predicting.set()
        assert cancellation._GONE.get().wait(10), "the request never learnt that its client left"
        return [], {}                                       # the last step ends all the same (no stacks: a 200)

    monkeypatch.setattr(route, "run_prediction", predict)
    with make_client(ModelRegistry({"default": oracle}), max_concurrent=1, max_admitted=2) as client:
        scenario, answers = _leaving_client(client.app, phantom_files, predicting)
        client.portal.call(scenario)
        assert answers["gone"][0] == 499
        assert client.app.state.slots._value == 1 and client.app.state.admissions._value == 2
        counted = _predicts_counted(client)
    assert len(counted) == 1 and 'status="499"' in counted[0], counted


def test_a_client_that_leaves_before_its_job_is_queued_leaves_no_job(
        oracle, phantom_files, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: ANN001
    """The client closes its connection while its submission's files are kept: it never learns the
    job's id, so no job is queued and nothing of its files stays (a 499)."""
    from service.api import reconstructions as route
    from service.core import cancellation

    keeping, submitted = threading.Event(), []
    real_keep = route.keep_decoded

    def keep(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        keeping.set()
        assert cancellation._GONE.get().wait(10), "the request never learnt that its client left"
        return real_keep(*args, **kwargs)

    monkeypatch.setattr(route, "keep_decoded", keep)
    with make_client(ModelRegistry({"default": oracle}), data_dir=tmp_path / "data") as client:
        monkeypatch.setattr(client.app.state.job_runner, "submit", submitted.append)
        scenario, answers = _leaving_client(client.app, phantom_files, keeping, "/v1/reconstructions")
        client.portal.call(scenario)
        assert answers["gone"][0] == 499
        assert submitted == [] and not any(client.app.state.job_store.counts().values())
    assert not [p for p in (tmp_path / "data").rglob("*") if p.is_file() and "inputs" in p.parts]
