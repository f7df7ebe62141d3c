"""The thin client and the ``svrnet`` CLI: against the real app in-process, over real HTTP (uvicorn),
and against ``httpx.MockTransport`` fakes of the contract (retries, reconstruction jobs, exit codes).

The oracle estimator is defined here rather than imported from ``tests/api/conftest.py`` so that this
file does not import torch (``tests/api/conftest.py`` builds a tiny exported model with it).
"""

from __future__ import annotations

import email
import email.policy
import io
import json
import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

import client._client as client_module
import client.cli as cli
from client import (BadRequest, Busy, Conflict, ConnectionFailed, JobFailed, NotFound, ServerError, SVRnetClient,
                    SVRnetError, Unauthorized, UnsupportedFile, UnusableInput, WaitTimeout)
from client.errors import error_from_response
from service.core.settings import Settings
from service.inference.estimator import PoseEstimate
from service.inference.model_file import ModelInfo
from service.inference.registry import ModelRegistry
from service.io.volume import Volume, write_volume
from service.main import create_app

REPO = Path(__file__).resolve().parents[2]
INFO = ModelInfo(name="oracle", version="0", backbone="oracle", label_type="anchor", input_size=64,
                 pixel_spacing_mm=2.0, variance_threshold=10.0, dropout_p=0.5, atlas_id="phantom",
                 trained_on="-", sha256="0" * 64)
SLICE_KEYS = {"index", "accepted", "reason", "geodesic_variance", "anchor_points_mm", "rotation", "rotation_vector",
              "quaternion_wxyz", "translation_mm", "atlas_from_voxel"}
MODEL_KEYS = {"name", "version", "backbone", "sha256", "input_size", "spacing_mm", "label_type",
              "variance_threshold", "trained_on"}


class OracleEstimator:
    """Same seam as ``tests/api/conftest.py``: returns ``truth`` (identity poses when unset)."""

    info = INFO

    def __init__(self) -> None:
        self.truth: np.ndarray | None = None

    def estimate(self, inputs: np.ndarray, mc_samples: int) -> PoseEstimate:
        n = len(inputs)
        truth = self.truth if self.truth is not None else np.broadcast_to(np.eye(4), (n, 4, 4))
        assert len(truth) == n, "truth and slices out of step"
        return PoseEstimate(np.array(truth, dtype=np.float64), np.full(n, 1.0), np.zeros(n, bool))


def make_test_client(**settings: object) -> TestClient:
    app = create_app(Settings(**settings), registry=ModelRegistry({"default": OracleEstimator()}))
    return TestClient(app, raise_server_exceptions=False)


@pytest.fixture(autouse=True)
def _no_ambient_config(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("SVRNET_API_KEY", raising=False)
    monkeypatch.delenv("SVRNET_SERVER", raising=False)


@pytest.fixture
def no_sleep(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """Record the client's retry/poll sleeps instead of sleeping."""
    slept: list[float] = []
    monkeypatch.setattr(client_module, "_sleep", slept.append)
    return slept


@pytest.fixture
def stack_file(tmp_path: Path) -> Path:
    data = np.random.default_rng(0).random((24, 24, 6)).astype(np.float32) * 100
    path = tmp_path / "stack.nii.gz"
    write_volume(Volume(data, np.diag([1.0, 1.0, 3.0, 1.0])), path)
    return path


@pytest.fixture
def mask_file(tmp_path: Path) -> Path:
    mask = np.zeros((24, 24, 6), np.uint8)
    mask[6:18, 6:18, :] = 1
    path = tmp_path / "stack_mask.nii.gz"
    write_volume(Volume(mask, np.diag([1.0, 1.0, 3.0, 1.0])), path)
    return path


@pytest.fixture
def app_client() -> Iterator[TestClient]:
    with make_test_client() as tc:
        yield tc


def parse_multipart(request: httpx.Request) -> tuple[dict[str, list[str]], list[tuple[str, str, str, bytes]]]:
    """(form fields, [(field, filename, content type, bytes)]) of a multipart request, via the stdlib."""
    head = f"Content-Type: {request.headers['content-type']}\r\nMIME-Version: 1.0\r\n\r\n".encode()
    msg = email.message_from_bytes(head + request.content, policy=email.policy.HTTP)
    assert msg.is_multipart()
    fields: dict[str, list[str]] = {}
    files = []
    for part in msg.iter_parts():
        name = part.get_param("name", header="content-disposition")
        payload = part.get_payload(decode=True)
        if part.get_filename() is None:
            fields.setdefault(name, []).append(payload.decode())
        else:
            files.append((name, part.get_filename(), part.get_content_type(), payload))
    return fields, files


def problem(status: int, detail: str, title: str = "Problem") -> dict[str, Any]:
    return {"type": "about:blank", "title": title, "status": status, "detail": detail, "request_id": "rid-1"}


# --- (a) the real app, in process ----------------------------------------------------------------------------


def test_predict_against_the_app_returns_the_contract(app_client: TestClient, stack_file: Path,
                                                      mask_file: Path) -> None:
    seen: list[tuple[int, int]] = []
    svr = SVRnetClient(http=app_client)
    result = svr.predict([stack_file], masks=[mask_file], mc_samples=3, bias_correction=False,
                         progress=lambda sent, total: seen.append((sent, total)))
    assert {"request_id", "model", "mc_samples", "variance_threshold", "stacks", "timing_ms"} <= set(result)
    assert result["mc_samples"] == 3 and result["variance_threshold"] == 10.0
    assert result["model"]["name"] == "default" and result["model"]["sha256"] == "0" * 64
    (stack,) = result["stacks"]
    assert stack["filename"] == "stack.nii.gz" and stack["shape"] == [24, 24, 6] and stack["slice_axis"] == 2
    assert [s["index"] for s in stack["slices"]] == list(range(6))
    assert all(SLICE_KEYS <= set(s) for s in stack["slices"])
    assert np.asarray(stack["slices"][0]["atlas_from_voxel"]).shape == (4, 4)
    assert seen[-1][0] == seen[-1][1] > stack_file.stat().st_size


def test_a_slice_order_reaches_the_stage_and_a_wrong_one_is_named(app_client: TestClient, stack_file: Path) -> None:
    svr = SVRnetClient(http=app_client)
    result = svr.predict([stack_file], slice_order="5,4,3,2,1,0", mc_samples=2, bias_correction=False)
    assert len(result["stacks"][0]["slices"]) == 6
    with pytest.raises(BadRequest) as e400:
        svr.predict([stack_file], slice_order="0,1,2", bias_correction=False)
    assert e400.value.status == 400 and "slice_order[0]" in e400.value.detail


def test_predict_without_options_uses_server_defaults(app_client: TestClient, stack_file: Path) -> None:
    result = SVRnetClient(http=app_client).predict([stack_file])
    assert result["mc_samples"] == 100 and len(result["stacks"][0]["slices"]) == 6


def test_models_and_health(app_client: TestClient) -> None:
    svr = SVRnetClient(http=app_client)
    (model,) = svr.models()
    assert MODEL_KEYS <= set(model) and model["name"] == "default"
    assert svr.health() == {"status": "ok"}


def test_app_errors_map_to_typed_exceptions(app_client: TestClient, stack_file: Path, tmp_path: Path) -> None:
    svr = SVRnetClient(http=app_client)
    wrong = tmp_path / "wrong_grid.nii.gz"
    write_volume(Volume(np.ones((24, 24, 5), np.uint8), np.diag([1.0, 1.0, 3.0, 1.0])), wrong)
    with pytest.raises(UnusableInput) as e422:
        svr.predict([stack_file], masks=[wrong], bias_correction=False)
    assert e422.value.status == 422 and "wrong_grid.nii.gz" in e422.value.detail and e422.value.request_id
    junk = tmp_path / "notes.nii.gz"
    junk.write_bytes(b"not an image " * 50)
    with pytest.raises(UnsupportedFile) as e415:
        svr.predict([junk])
    assert "notes.nii.gz" in e415.value.detail and "notes.nii.gz" in str(e415.value)
    with pytest.raises(NotFound, match="nope"):
        svr.predict([stack_file], model="nope")
    with pytest.raises(ValueError, match="masks"):
        svr.predict([stack_file, stack_file], masks=[stack_file])


def test_api_keys(stack_file: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with make_test_client(api_keys="k") as tc:
        with pytest.raises(Unauthorized) as e:
            SVRnetClient(http=tc).models()
        assert e.value.status == 401 and "API key" in e.value.detail
        with pytest.raises(Unauthorized):
            SVRnetClient(http=tc, api_key="wrong").predict([stack_file])
        assert SVRnetClient(http=tc, api_key="k").models()[0]["name"] == "default"
        assert SVRnetClient(http=tc, api_key="k").predict([stack_file], bias_correction=False)["stacks"]
        monkeypatch.setenv("SVRNET_API_KEY", "k")
        assert SVRnetClient(http=tc).models()[0]["name"] == "default"


@pytest.fixture
def live_server() -> Iterator[str]:
    """A real uvicorn on 127.0.0.1 (free port) serving the app in a thread; stopped within a few seconds."""
    import uvicorn

    app = create_app(Settings(), registry=ModelRegistry({"default": OracleEstimator()}))
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on", timeout_graceful_shutdown=2))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not server.started and thread.is_alive() and time.monotonic() < deadline:
        time.sleep(0.02)
    try:
        assert server.started, "uvicorn did not start"
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=5)
        sock.close()
        assert not thread.is_alive(), "uvicorn did not stop"


def test_over_real_http(live_server: str, stack_file: Path) -> None:
    with SVRnetClient(live_server, retries=0) as svr:
        assert svr.models()[0]["name"] == "default"
        result = svr.predict([stack_file, stack_file], mc_samples=2, bias_correction=False)
        assert [s["filename"] for s in result["stacks"]] == ["stack.nii.gz", "stack.nii.gz"]
        assert result["mc_samples"] == 2 and len(result["stacks"][1]["slices"]) == 6


# --- (b) retries, errors and the upload body -----------------------------------------------------------------


def mock(handler: Callable[[httpx.Request], httpx.Response], **kwargs: Any) -> SVRnetClient:
    return SVRnetClient("http://svr.test", transport=httpx.MockTransport(handler), **kwargs)


def test_503_twice_then_success_resends_the_whole_body(stack_file: Path, mask_file: Path,
                                                        no_sleep: list[float]) -> None:
    calls: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(request)
        if len(calls) < 3:
            return httpx.Response(503, headers={"Retry-After": "0"}, json=problem(503, "busy"))
        return httpx.Response(200, json={"stacks": []})

    progress: list[tuple[int, int]] = []
    result = mock(handler).predict([stack_file], [mask_file], mc_samples=7, variance_threshold=2.5,
                                   progress=lambda s, t: progress.append((s, t)))
    assert result == {"stacks": []} and len(calls) == 3 and no_sleep == [0.0, 0.0]
    bodies = {c.content for c in calls}
    assert len(bodies) == 1                                   # the same body, complete, every attempt
    request = calls[-1]
    assert request.url.path == "/v1/predict" and request.method == "POST"
    assert int(request.headers["content-length"]) == len(request.content)
    assert "authorization" not in request.headers
    fields, files = parse_multipart(request)
    assert fields == {"mc_samples": ["7"], "variance_threshold": ["2.5"]}   # only the options given
    assert [(f[0], f[1], f[2]) for f in files] == [("stacks", "stack.nii.gz", "application/octet-stream"),
                                                   ("masks", "stack_mask.nii.gz", "application/octet-stream")]
    assert files[0][3] == stack_file.read_bytes() and files[1][3] == mask_file.read_bytes()
    assert progress[-1] == (len(request.content), len(request.content))


def test_upload_progress_reaches_the_total(stack_file: Path) -> None:
    big = stack_file.parent / "big.nii"
    big.write_bytes(bytes(range(256)) * 4000)                 # ~1 MB: several chunks
    got: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        got.append(request)
        return httpx.Response(200, json={})

    seen: list[tuple[int, int]] = []
    mock(handler).predict([big, stack_file], bias_correction=True, model="m", image_consistency=False,
                          masks_hold_csf=True, progress=lambda s, t: seen.append((s, t)))
    total = len(got[0].content)
    assert len(seen) > 4 and all(t == total for _, t in seen)
    assert [s for s, _ in seen] == sorted(s for s, _ in seen) and seen[0][0] == 0 and seen[-1][0] == total
    fields, files = parse_multipart(got[0])
    assert fields == {"bias_correction": ["true"], "model": ["m"], "image_consistency": ["false"],
                      "masks_hold_csf": ["true"]}
    assert [(f[0], f[1]) for f in files] == [("stacks", "big.nii"), ("stacks", "stack.nii.gz")]
    assert files[0][3] == big.read_bytes()


@pytest.mark.parametrize(("retry_after", "calls_made", "sleeps"), [("2", 4, [2.0, 2.0, 2.0]), ("100", 1, [])])
def test_always_busy_raises_busy(no_sleep: list[float], retry_after: str, calls_made: int,
                                 sleeps: list[float]) -> None:
    """Retry-After is honoured; a wait longer than 30 s is not shortened but handed to the caller."""
    calls = []

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(request)
        return httpx.Response(503, headers={"Retry-After": retry_after}, json=problem(503, "saturated", "Busy"))

    with pytest.raises(Busy) as e:
        mock(handler, retries=3).models()
    assert len(calls) == calls_made and e.value.status == 503 and e.value.retry_after_s == float(retry_after)
    assert no_sleep == sleeps and "saturated" in str(e.value)


def test_an_upload_is_resent_only_when_the_server_said_when(no_sleep: list[float], stack_file: Path) -> None:
    calls = []

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(request)
        return httpx.Response(503, text="bad gateway of some proxy")

    with pytest.raises(Busy):
        mock(handler, retries=3).predict([stack_file])
    assert len(calls) == 1 and no_sleep == []


def test_a_redirect_is_an_error_not_a_volume(tmp_path: Path) -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(308, headers={"Location": "https://svr.test/"}, text="<html>moved</html>")

    svr = mock(handler)
    with pytest.raises(SVRnetError, match="redirect .308. to https://svr.test/"):
        svr.download_volume("job1", tmp_path / "v.nii.gz")
    assert not (tmp_path / "v.nii.gz").exists()
    with pytest.raises(SVRnetError, match="redirect"):
        svr.cancel("job1")


def test_429_without_retry_after_backs_off_exponentially(no_sleep: list[float]) -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(429, text="slow down")

    with pytest.raises(Busy) as e:
        mock(handler, retries=3, backoff_s=0.5).health()
    assert no_sleep == [0.5, 1.0, 2.0] and e.value.status == 429 and e.value.detail == "slow down"


def test_connection_errors_retry_gets_only(no_sleep: list[float], stack_file: Path) -> None:
    calls = []

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(request.method)
        raise httpx.ConnectError("connection refused", request=request)

    with pytest.raises(ConnectionFailed, match="connection refused") as e:
        mock(handler, retries=2).models()
    assert calls == ["GET"] * 3 and e.value.status is None
    calls.clear()
    with pytest.raises(ConnectionFailed):
        mock(handler, retries=2).predict([stack_file])
    assert calls == ["POST"]


def test_connection_to_a_closed_port() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(ConnectionFailed), SVRnetClient(f"http://127.0.0.1:{port}", retries=0) as svr:
        svr.health()


@pytest.mark.parametrize(("status", "cls"), [(400, BadRequest), (401, Unauthorized), (404, NotFound),
                                             (409, Conflict), (415, UnsupportedFile), (422, UnusableInput),
                                             (500, ServerError), (502, ServerError), (418, BadRequest)])
def test_error_mapping(status: int, cls: type[SVRnetError]) -> None:
    err = error_from_response(httpx.Response(status, json=problem(status, "field x: bad", "T"),
                                             headers={"content-type": "application/problem+json"}))
    assert type(err) is cls and err.status == status and err.detail == "field x: bad" and err.title == "T"
    assert err.request_id == "rid-1"
    plain = error_from_response(httpx.Response(status, text="<html>oops</html>", headers={"x-request-id": "h1"}))
    assert type(plain) is cls and "oops" in plain.detail and plain.request_id == "h1"


def test_api_key_header_and_non_json_server_error() -> None:
    seen = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request.headers.get("authorization"))
        return httpx.Response(500, text="Internal Server Error")

    with pytest.raises(ServerError, match="Internal Server Error"):
        mock(handler, api_key="s3cret").models()
    assert seen == ["Bearer s3cret"]


# --- (c) reconstruction jobs against a fake of the contract ----------------------------------------------------


class FakeJobs:
    """The contract's reconstruction routes: each status poll moves a job queued -> running -> succeeded."""

    VOLUME = b"\x1f\x8b fake nifti volume" * 1000
    PREVIEW = b"\x89PNG fake"

    def __init__(self, outcome: str = "succeeded") -> None:
        self.outcome = outcome
        self.jobs: dict[str, dict[str, Any]] = {}
        self.uploads: list[tuple[dict, list]] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        path, method = request.url.path, request.method
        if path == "/v1/reconstructions" and method == "POST":
            self.uploads.append(parse_multipart(request))
            job_id = f"job{len(self.jobs) + 1}"
            self.jobs[job_id] = {"job_id": job_id, "status": "queued", "stage": "queued", "progress": 0.0,
                                 "error": None, "created_at": "t0", "updated_at": "t0", "result_url": None,
                                 "preview_url": None, "report": None, "polls": 0}
            url = f"/v1/reconstructions/{job_id}"
            return httpx.Response(202, headers={"Location": url},
                                  json={"job_id": job_id, "status": "queued", "status_url": url})
        m = re.fullmatch(r"/v1/reconstructions/([^/]+)(/volume|/preview\.png|/poses)?", path)
        if not m or m.group(1) not in self.jobs:
            return httpx.Response(404, json=problem(404, f"job: unknown job {m.group(1) if m else path}"))
        job = self.jobs[m.group(1)]
        if method == "DELETE" and not m.group(2):
            del self.jobs[m.group(1)]
            return httpx.Response(204)
        if m.group(2):
            if job["status"] != "succeeded":
                return httpx.Response(409, json=problem(409, f"job {job['job_id']} is {job['status']}"))
            if m.group(2) == "/poses":
                return httpx.Response(200, json=dict(PREDICT_BODY, refined_by={"job_id": job["job_id"]}))
            return httpx.Response(200, content=self.VOLUME if m.group(2) == "/volume" else self.PREVIEW)
        job["polls"] += 1
        if job["polls"] == 2:
            job.update(status="running", stage="svr", progress=0.5)
        elif job["polls"] >= 3 and self.outcome == "succeeded":
            job.update(status="succeeded", stage="done", progress=1.0,
                       result_url=f"/v1/reconstructions/{job['job_id']}/volume",
                       preview_url=f"/v1/reconstructions/{job['job_id']}/preview.png", report={"slices": []})
        elif job["polls"] >= 3 and self.outcome != "running":
            job.update(status=self.outcome, error="SVR diverged" if self.outcome == "failed" else None)
        return httpx.Response(200, json={k: v for k, v in job.items() if k != "polls"})


def test_job_flow(stack_file: Path, mask_file: Path, tmp_path: Path, no_sleep: list[float]) -> None:
    fake = FakeJobs()
    svr = mock(fake)
    poses = {"request_id": "r", "stacks": [{"index": 0, "slices": []}]}
    job = svr.reconstruct([stack_file], [mask_file], poses=poses, resolution_mm=0.8, svr_iterations=3)
    assert job == {"job_id": "job1", "status": "queued", "status_url": "/v1/reconstructions/job1"}
    fields, files = fake.uploads[0]
    assert fields == {"resolution_mm": ["0.8"], "svr_iterations": ["3"]}
    assert [(f[0], f[2]) for f in files] == [("stacks", "application/octet-stream"),
                                             ("masks", "application/octet-stream"), ("poses", "application/json")]
    assert json.loads(files[2][3]) == poses
    assert svr.status("job1")["status"] == "queued"
    with pytest.raises(Conflict) as e409:
        svr.download_volume("job1", tmp_path / "early.nii.gz")
    assert e409.value.status == 409 and not (tmp_path / "early.nii.gz").exists()
    seen: list[tuple[str, float]] = []
    final = svr.wait("job1", poll_s=0.0, on_progress=lambda s: seen.append((s["status"], s["progress"])))
    assert final["status"] == "succeeded" and seen == [("running", 0.5), ("succeeded", 1.0)]
    out = svr.download_volume("job1", tmp_path / "recon.nii.gz")
    assert out.read_bytes() == FakeJobs.VOLUME and not list(tmp_path.glob(".*part*"))
    assert svr.download_preview("job1", tmp_path / "p.png").read_bytes() == FakeJobs.PREVIEW
    assert svr.cancel("job1") is None
    with pytest.raises(NotFound, match="job1"):
        svr.status("job1")


def test_poses_from_a_file_and_failed_and_cancelled_jobs(stack_file: Path, tmp_path: Path,
                                                         no_sleep: list[float]) -> None:
    poses = tmp_path / "poses.json"
    poses.write_text('{"stacks": []}')
    for outcome in ("failed", "cancelled"):
        fake = FakeJobs(outcome)
        svr = mock(fake)
        job_id = svr.reconstruct([stack_file], poses=poses)["job_id"]
        assert fake.uploads[0][1][-1][:3] == ("poses", "poses.json", "application/json")
        with pytest.raises(JobFailed) as e:
            svr.wait(job_id, poll_s=0.0)
        assert e.value.job_status == outcome and e.value.job_id == job_id
        assert ("SVR diverged" in str(e.value)) == (outcome == "failed")


def test_wait_times_out() -> None:
    svr = mock(FakeJobs("running"))
    job_id = svr.reconstruct([__file__])["job_id"]
    with pytest.raises(WaitTimeout) as e:
        svr.wait(job_id, poll_s=0.01, timeout_s=0.05)
    assert e.value.job["status"] == "running"


# --- (d) the CLI ---------------------------------------------------------------------------------------------


PREDICT_BODY = {
    "request_id": "abc", "model": {"name": "default", "version": "1", "backbone": "b", "sha256": "0" * 64},
    "mc_samples": 5, "variance_threshold": 10.0, "timing_ms": {"total": 12.0},
    "stacks": [{"index": 0, "filename": "stack.nii.gz", "shape": [24, 24, 4], "spacing_mm": [1, 1, 3],
                "slice_axis": 2, "slices": [
                    {"index": 0, "accepted": True, "reason": None, "geodesic_variance": 1.0},
                    {"index": 1, "accepted": True, "reason": None, "geodesic_variance": 3.0},
                    {"index": 2, "accepted": False, "reason": "high_variance", "geodesic_variance": 40.0},
                    {"index": 3, "accepted": False, "reason": "empty", "geodesic_variance": None}],
                "localisation": {"method": "network", "brain_volume_ml": 312.4, "confidence": 0.93}}],
}


def masks_archive() -> bytes:
    """What /v1/masks answers, plus a member that names a path (never written)."""
    import io
    import zipfile

    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as z:
        z.writestr("stack_mask.nii.gz", b"mask bytes")
        z.writestr("../escape.json", b"{}")
        z.writestr("report.json", json.dumps({"stacks": [{"filename": "stack.nii.gz", "mask": "stack_mask.nii.gz",
                                                          "brain_volume_ml": 301.0, "confidence": 0.91,
                                                          "slices_with_brain": 17}]}))
    return buffer.getvalue()


class FakeServer:
    """/v1/predict and /v1/models with an optional key, plus the job routes; ``mode`` forces failures."""

    def __init__(self, key: str | None = None, mode: str = "ok", jobs: str = "succeeded") -> None:
        self.key, self.mode = key, mode
        self.jobs = FakeJobs(jobs)
        self.requests: list[httpx.Request] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        if self.mode == "down":
            raise httpx.ConnectError("[Errno 111] Connection refused", request=request)
        if self.key and request.headers.get("authorization") != f"Bearer {self.key}":
            return httpx.Response(401, json=problem(401, "Authorization: a valid API key is required"))
        if self.mode == "422":
            return httpx.Response(422, json=problem(422, "stacks: flat.nii.gz is a 2D image", "Unusable image"))
        if request.url.path == "/v1/predict":
            return httpx.Response(200, json=PREDICT_BODY)
        if request.url.path == "/v1/masks":
            return httpx.Response(200, content=masks_archive(), headers={"content-type": "application/zip"})
        if request.url.path == "/v1/models":
            return httpx.Response(200, json=[{"name": "default", "version": "1", "backbone": "b",
                                              "sha256": "0" * 64, "input_size": 128, "spacing_mm": 0.8,
                                              "label_type": "anchor", "variance_threshold": 10.0,
                                              "trained_on": "atlas"}])
        return self.jobs(request)


@pytest.fixture
def fake_cli(monkeypatch: pytest.MonkeyPatch, no_sleep: list[float]) -> Callable[..., tuple[FakeServer, list]]:
    def install(**kwargs: Any) -> tuple[FakeServer, list]:
        fake = FakeServer(**kwargs)
        made: list[tuple[str, str | None]] = []

        def factory(server: str, api_key: str | None) -> SVRnetClient:
            made.append((server, api_key))
            return SVRnetClient(server, api_key=api_key, transport=httpx.MockTransport(fake), retries=1)

        monkeypatch.setattr(cli, "make_client", factory)
        return fake, made

    return install


def invoke(args: list[str], **env: str) -> Any:
    return CliRunner().invoke(cli.app, args, env={"COLUMNS": "200", **env})


def test_cli_predict_writes_json_and_prints_a_summary(fake_cli: Callable, stack_file: Path, tmp_path: Path) -> None:
    fake, made = fake_cli()
    out = tmp_path / "poses.json"
    r = invoke(["predict", str(stack_file), "--out", str(out), "--mc-samples", "5", "--no-bias-correction",
                "--no-image-consistency", "--masks-hold-csf", "--server", "http://scanner:9000"])
    assert r.exit_code == 0, r.output
    assert json.loads(out.read_text()) == PREDICT_BODY
    assert made == [("http://scanner:9000", None)]
    assert "stack.nii.gz" in r.stdout and "empty 1, high_variance 1" in r.stdout and "3" in r.stdout
    assert "variance" in r.stdout and "the stack's medians" in r.stdout and "abc" in r.stdout
    assert "312 ml" in r.stdout and "(0.93)" in r.stdout and "2 of 4" in r.stdout
    fields, files = parse_multipart(fake.requests[0])
    assert fields == {"mc_samples": ["5"], "bias_correction": ["false"], "image_consistency": ["false"],
                      "masks_hold_csf": ["true"]}
    assert files[0][1] == "stack.nii.gz"


@pytest.mark.parametrize("name", ["axial1_lr.nii.gz", "sub-000_ses-01_T2w_haste_coronal_run-2.nii.gz"])
def test_the_summary_fits_an_80_column_terminal_and_cuts_no_cell_short(name: str) -> None:
    from rich.console import Console

    stack = PREDICT_BODY["stacks"][0]
    reasons = ["empty", "high_expected_error", "outside_atlas", "inconsistent_with_stack"]
    body = {**PREDICT_BODY, "max_expected_error_mm": 4.2, "stacks": [
        {**stack, "filename": name, "slices": [{"index": i, "accepted": False, "reason": reasons[i % 4],
                                                "expected_error_mm": 50.0, "geodesic_variance": 123.0}
                                               for i in range(40)]}] * 2}
    console = Console(width=80, record=True, file=io.StringIO())
    console.print(cli.summarise(body))
    text = console.export_text()
    assert max(len(line) for line in text.splitlines()) <= 80 and "…" not in text
    assert "0 of 40" in text and "50.0 mm" in text and "123" in text and "312 ml" in text and "variance" in text
    if len(name) <= cli.NAME_WIDTH:
        assert name in text                                       # a usual name stays whole
    else:                                                         # a long one folds, nothing of it dropped
        assert all(name[i:i + cli.NAME_WIDTH] in text for i in range(0, len(name), cli.NAME_WIDTH))


def test_cli_masks_writes_the_masks_and_nothing_outside(fake_cli: Callable, stack_file: Path, tmp_path: Path) -> None:
    fake, _ = fake_cli()
    out = tmp_path / "deep" / "masks"
    r = invoke(["masks", str(stack_file), "--out-dir", str(out), "--model", "default"])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in out.iterdir()) == ["report.json", "stack_mask.nii.gz"]
    assert not (tmp_path / "deep" / "escape.json").exists()
    assert (out / "stack_mask.nii.gz").read_bytes() == b"mask bytes"
    assert "stack_mask.nii.gz" in r.stdout and "0.91" in r.stdout and "301" in r.stdout
    fields, files = parse_multipart(fake.requests[0])
    assert fake.requests[0].url.path == "/v1/masks" and fields == {"model": ["default"]}
    assert [f[:2] for f in files] == [("stacks", "stack.nii.gz")]


def test_cli_sends_each_slice_order_as_one_field(fake_cli: Callable, stack_file: Path) -> None:
    fake, _ = fake_cli()
    r = invoke(["predict", str(stack_file), str(stack_file), "--slice-order", "interleaved",
                "--slice-order", "0,2,4,1,3,5"])
    assert r.exit_code == 0, r.output
    fields, _ = parse_multipart(fake.requests[0])
    assert fields == {"slice_order": ["interleaved", "0,2,4,1,3,5"]}


def test_cli_server_and_key_from_the_environment(fake_cli: Callable) -> None:
    fake, made = fake_cli(key="k")
    r = invoke(["models"], SVRNET_SERVER="http://env:1234", SVRNET_API_KEY="k")
    assert r.exit_code == 0, r.output
    assert made == [("http://env:1234", "k")] and "default" in r.stdout and "atlas" in r.stdout


@pytest.mark.parametrize(("kwargs", "args", "code", "needle"), [
    ({"mode": "down"}, ["models"], 3, "Connection refused"),
    ({"key": "k"}, ["models"], 4, "API key"),
    ({"mode": "422"}, ["predict", "STACK"], 5, "flat.nii.gz"),
    ({}, ["status", "nojob"], 6, "nojob"),
])
def test_cli_exit_codes(fake_cli: Callable, stack_file: Path, kwargs: dict, args: list[str], code: int,
                        needle: str) -> None:
    fake_cli(**kwargs)
    r = invoke([str(stack_file) if a == "STACK" else a for a in args])
    assert r.exit_code == code, r.output
    assert r.stderr.startswith("error: ") and needle in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert "Traceback" not in r.output and r.stdout == ""


def test_cli_usage_errors_and_help(fake_cli: Callable, stack_file: Path, tmp_path: Path) -> None:
    fake, _ = fake_cli()
    assert invoke(["predict", str(stack_file), str(stack_file), "--mask", str(stack_file)]).exit_code == 2
    assert invoke(["predict", str(tmp_path / "missing.nii.gz")]).exit_code == 2
    assert invoke(["predict", str(stack_file), "--threshold", "0"]).exit_code == 2
    for args in (["status", " "], ["cancel", ""], ["reconstruct", str(stack_file), "--out", str(tmp_path / "no" / "r.nii.gz")],
                 ["predict", str(stack_file), "--out", str(tmp_path / "no" / "p.json")]):
        r = invoke(args)
        assert r.exit_code == 2 and "Traceback" not in r.output, (args, r.output)
    assert not fake.requests                                  # refused before anything was uploaded
    help_text = invoke(["--help"]).stdout
    assert "Exit codes" in help_text and "3 connection failed" in help_text and "10 conflict" in help_text
    assert "Exit codes" in invoke(["predict", "--help"]).stdout
    assert "Exit codes:" in cli.__doc__


def test_cli_reconstruct_wait_downloads(fake_cli: Callable, stack_file: Path, tmp_path: Path) -> None:
    fake, _ = fake_cli()
    poses = tmp_path / "poses.json"
    poses.write_text(json.dumps(PREDICT_BODY))
    out, preview, refined = tmp_path / "recon.nii.gz", tmp_path / "preview.png", tmp_path / "refined.json"
    r = invoke(["reconstruct", str(stack_file), "--poses", str(poses), "--resolution", "0.8", "--svr-iterations",
                "2", "--wait", "--poll", "0.05", "--out", str(out), "--preview", str(preview),
                "--poses-out", str(refined), "--no-atlas-frame", "--slice-order", "interleaved"])
    assert r.exit_code == 0, r.output
    assert out.read_bytes() == FakeJobs.VOLUME and preview.read_bytes() == FakeJobs.PREVIEW
    assert json.loads(refined.read_text())["refined_by"] == {"job_id": "job1"}
    assert "job1" in r.stdout and "succeeded" in r.stdout
    fields, files = fake.jobs.uploads[0]
    assert fields == {"resolution_mm": ["0.8"], "svr_iterations": ["2"], "atlas_frame": ["false"],
                      "slice_order": ["interleaved"]} and files[-1][0] == "poses"


def test_cli_reconstruct_without_wait_and_failed_job(fake_cli: Callable, stack_file: Path, tmp_path: Path) -> None:
    fake_cli()
    r = invoke(["reconstruct", str(stack_file)])
    assert r.exit_code == 0 and "svrnet status job1" in r.stdout
    fake_cli(jobs="failed")
    r = invoke(["reconstruct", str(stack_file), "--wait", "--poll", "0.05", "--out", str(tmp_path / "x.nii.gz")])
    assert r.exit_code == 8 and "SVR diverged" in r.stderr and not (tmp_path / "x.nii.gz").exists()


def test_cli_status_cancel_and_conflict(fake_cli: Callable, stack_file: Path) -> None:
    fake, _ = fake_cli()
    assert invoke(["reconstruct", str(stack_file)]).exit_code == 0
    r = invoke(["status", "job1"])
    assert r.exit_code == 0 and "queued" in r.stdout
    r = invoke(["status", "job1", "--json"])
    assert r.exit_code == 0 and json.loads(r.stdout)["job_id"] == "job1"
    assert invoke(["cancel", "job1"]).exit_code == 0
    assert invoke(["cancel", "job1"]).exit_code == 6


# --- (e) the client stays thin ------------------------------------------------------------------------------


def test_import_client_pulls_in_nothing_heavy() -> None:
    code = ("import sys, client, client.cli; "
            "bad = [m for m in sys.modules if m.split('.')[0] in "
            "('torch', 'onnxruntime', 'SimpleITK', 'numpy', 'service', 'model_export', 'scipy')]; "
            "print(','.join(sorted(bad)))")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == ""


def test_cli_timeout_from_the_environment(stack_file: Path) -> None:
    r = invoke(["models", "--server", "http://127.0.0.1:9"], SVRNET_TIMEOUT="soon")
    assert r.exit_code == 2 and "SVRNET_TIMEOUT" in r.output
    assert cli.make_client("http://x", None)._http.timeout.read == 300.0
