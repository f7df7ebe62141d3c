"""Uploads decode within bounded memory however many clients send at once: reconstructions and masks
take a processing slot like predictions (503 with Retry-After when none is free, before the upload is
read), and at most
``READ_WORKERS`` files are decoded at a time in the whole process."""

from __future__ import annotations

import asyncio
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from service.api import uploads
from service.inference.registry import ModelRegistry
from tests.support import corpus
from tests.api.conftest import make_client
from tests.api.test_operations import _call_without_reading_the_body


@pytest.mark.parametrize("route", ["/v1/reconstructions", "/v1/masks", "/v1/predict"])
def test_a_saturated_server_refuses_uploads_before_reading_them(oracle, route: str) -> None:  # noqa: ANN001
    with make_client(ModelRegistry({"default": oracle}), max_concurrent=1, retry_after_s=4) as client:
        client.app.state.slots._value = 0
        status, headers, read = _call_without_reading_the_body(client.app, route, [])
        assert (status, read, headers["retry-after"]) == (503, False, "4")
        r = client.post(route, files=[("stacks", ("s.nii.gz", b"x"))])
        assert r.status_code == 503 and r.headers["retry-after"] == "4"


def test_requests_that_arrive_together_are_refused_before_their_uploads(oracle) -> None:  # noqa: ANN001
    """One slot, two uploads at the same moment: the second is refused (503) while the first is still
    uploading, its body unread; the first's slot is free again once it has its answer."""
    with make_client(ModelRegistry({"default": oracle}), max_concurrent=1, retry_after_s=3) as client:
        app, answers, read = client.app, {}, {"second": False}

        def scope() -> dict:
            return {"type": "http", "method": "POST", "path": "/v1/predict", "raw_path": b"/v1/predict",
                    "query_string": b"", "headers": [(b"content-type", b"multipart/form-data; boundary=xx")],
                    "app": app, "root_path": "", "scheme": "http", "server": ("test", 80), "client": ("test", 1)}

        def sender(name: str):  # noqa: ANN202
            async def send(message: dict) -> None:
                if message["type"] == "http.response.start":
                    answers[name] = (message["status"], {k.decode(): v.decode() for k, v in message["headers"]})
            return send

        async def scenario() -> None:
            uploading, finish = asyncio.Event(), asyncio.Event()

            async def slow() -> dict:                      # the first client's body, still on its way
                uploading.set()
                await finish.wait()
                return {"type": "http.request", "body": b"x" * 1000, "more_body": False}

            async def quick() -> dict:
                read["second"] = True
                return {"type": "http.request", "body": b"x" * 1000, "more_body": False}

            first = asyncio.create_task(app(scope(), slow, sender("first")))
            await uploading.wait()
            await app(scope(), quick, sender("second"))
            finish.set()
            await first

        asyncio.run(scenario())
        status, headers = answers["second"]
        assert (status, read["second"], headers["retry-after"]) == (503, False, "3")
        assert answers["first"][0] == 400                  # its garbage body, read and refused: not a 503
        assert app.state.slots._value == 1                 # its slot given back


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
