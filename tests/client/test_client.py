"""The thin client: against the real app in-process, over real HTTP (uvicorn), and against
``httpx.MockTransport`` fakes of the contract (retries, errors, reconstruction jobs); the CLI's own
tests are in ``test_cli.py``.

The oracle estimator is defined here rather than imported from ``tests/api/conftest.py`` so that this
file does not import torch (``tests/api/conftest.py`` builds a tiny exported model with it).
"""

from __future__ import annotations

import json
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
import typer
from fastapi.testclient import TestClient

from client import (BadRequest, Busy, Conflict, ConnectionFailed, JobFailed, KeyReused, NotFound, OriginNotAllowed,
                    ServerError, SVRnetClient, SVRnetError, Unauthorized, UnsupportedFile, UnusableInput)
from client import stream as client_stream
from client.errors import ArgumentError, error_from_response
from client.exits import EXIT_CONNECTION, EXIT_HELP, EXIT_INTERRUPTED, errors, exit_code_for
from service.core.settings import Settings
from service.inference.estimator import PoseEstimate
from service.inference.model_file import ModelInfo
from service.inference.registry import ModelRegistry
from service.io.volume import Volume, write_volume
from service.main import create_app
from tests.support.client_fakes import FakeJobs, parse_multipart, problem, send_json
from tests.support.local_client import LocalClient

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
    return LocalClient(app, raise_server_exceptions=False)


@pytest.fixture
def app_client() -> Iterator[TestClient]:
    with make_test_client() as tc:
        yield tc


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
    assert e400.value.status == 400 and "slice_order, stack 0" in e400.value.detail


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
        assert e.value.status == 401 and "API key" in e.value.detail and e.value.key_sent is False
        with pytest.raises(Unauthorized) as e:
            SVRnetClient(http=tc, api_key="wrong").predict([stack_file])
        assert e.value.key_sent is True                   # the CLI then says the key was refused, not missing
        assert SVRnetClient(http=tc, api_key="k").models()[0]["name"] == "default"
        assert SVRnetClient(http=tc, api_key="k").predict([stack_file], bias_correction=False)["stacks"]
        monkeypatch.setenv("SVRNET_API_KEY", "k")
        assert SVRnetClient(http=tc).models()[0]["name"] == "default"
        assert SVRnetClient(http=tc, api_key="k\r\n").models()[0]["name"] == "default"    # a key file's line end
        for bad in ("k\x01ey", "k ey", "kéy"):                                # no header can carry them
            with pytest.raises(ArgumentError) as refused:
                SVRnetClient(http=tc, api_key=bad)
            assert bad not in str(refused.value) and "api_key" in str(refused.value)


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


def test_over_real_http(live_server: str, stack_file: Path, tmp_path: Path) -> None:
    other = tmp_path / "second" / stack_file.name                      # another stack of the same file name
    other.parent.mkdir()
    data = np.random.default_rng(1).random((24, 24, 6)).astype(np.float32) * 100
    write_volume(Volume(data, np.diag([1.0, 1.0, 3.0, 1.0])), other)
    with SVRnetClient(live_server, retries=0) as svr:
        assert svr.models()[0]["name"] == "default"
        result = svr.predict([stack_file, other], mc_samples=2, bias_correction=False)
        assert [s["filename"] for s in result["stacks"]] == ["stack.nii.gz", "stack.nii.gz"]
        assert result["mc_samples"] == 2 and len(result["stacks"][1]["slices"]) == 6


# --- (b) retries, errors and the upload body -----------------------------------------------------------------


def mock(handler: Callable[[httpx.Request], httpx.Response], **kwargs: Any) -> SVRnetClient:
    return SVRnetClient("http://svr.test", transport=httpx.MockTransport(handler), **kwargs)


def test_the_library_takes_paths_and_numbers_as_a_script_holds_them(stack_file: Path, tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """``~`` expanded where a path goes in or out, as a shell expands the command line's; a slice thickness
    read from a header (a numpy scalar) sent as a number; a stack that is not there named as such, not
    as a corrupt file; the library's own refusal importable from the package."""
    import shutil

    from client import ArgumentError as exported
    from client.scanner_stack import read_stack

    assert exported is ArgumentError
    monkeypatch.setenv("HOME", str(tmp_path))
    shutil.copy(stack_file, tmp_path / "ax.nii.gz")
    sent: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        sent.append(request)
        if request.url.path.endswith("/volume"):
            return httpx.Response(200, content=b"volume", headers={"content-type": "application/gzip"})
        return httpx.Response(202, json={"job_id": "j", "status": "queued", "status_url": "/v1/reconstructions/j"})

    with mock(handler) as svr:
        svr.reconstruct(["~/ax.nii.gz"], slice_thickness_mm=np.float32(3.0))
        assert svr.download_volume("j", "~/recon.nii.gz") == tmp_path / "recon.nii.gz"
    fields, _ = parse_multipart(sent[0])
    assert fields["slice_thickness_mm"] == ["3.0"]
    assert (tmp_path / "recon.nii.gz").read_bytes() == b"volume" and not Path("~").exists()
    with pytest.raises(FileNotFoundError):
        read_stack(tmp_path / "absent.nii.gz")


def test_a_server_given_without_its_scheme_is_refused_by_the_library_before_any_call(stack_file: Path) -> None:
    """The check sat in the command line alone: a script's ``SVRnetClient("127.0.0.1:8000")`` failed at
    its first call as a connection error, and ``svrnet stream`` said "connection failed"."""
    from client.scanner_stack import read_stack

    for make in (lambda: SVRnetClient("127.0.0.1:8000"),
                 lambda: client_stream.stream_stacks([read_stack(stack_file)], "127.0.0.1:8000")):
        with pytest.raises(ArgumentError, match="server: '127.0.0.1:8000': give the server's URL with its scheme"):
            make()
    assert client_stream.stream_url("wss://svr.example/") == "wss://svr.example/v1/stream"


def test_a_stream_reads_the_server_and_key_from_the_environment_as_the_client_does(
        stack_file: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from client.scanner_stack import read_stack

    seen: list[tuple[str, str | None]] = []

    def connect(url: str, key: str | None, timeout_s: float) -> None:
        seen.append((url, key))
        raise ConnectionFailed("stop here")

    monkeypatch.setattr(client_stream, "_connect", connect)
    monkeypatch.setenv("SVRNET_SERVER", "https://svr.example:8443")
    monkeypatch.setenv("SVRNET_API_KEY", "k-env")
    with pytest.raises(ConnectionFailed):
        client_stream.stream_stacks([read_stack(stack_file)])
    with pytest.raises(ConnectionFailed):
        client_stream.stream_stacks([read_stack(stack_file)], "http://other:8000", api_key="k-given")
    assert seen == [("wss://svr.example:8443/v1/stream", "k-env"), ("ws://other:8000/v1/stream", "k-given")]


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


def test_a_full_disk_is_waited_out_and_a_late_upload_is_the_connection_s_fault(stack_file: Path,
                                                                              no_sleep: list[float]) -> None:
    """507 with ``Retry-After`` (the server's disk filled; the files are not at fault) is retried as a 503
    is; a 408 (the upload did not arrive in time) is a connection failure (exit 3), not bad input (5)."""
    calls: list[httpx.Request] = []

    def full_then_free(request: httpx.Request) -> httpx.Response:
        calls.append(request)
        if len(calls) == 1:
            return httpx.Response(507, headers={"Retry-After": "1"}, json=problem(507, "disk full", "Insufficient storage"))
        return httpx.Response(200, json={"stacks": []})

    assert mock(full_then_free).predict([stack_file]) == {"stacks": []} and len(calls) == 2 and len(no_sleep) == 1
    for wrong in ([], {"stacks": None}):                       # an answer of another server: nothing written from it
        with pytest.raises(ConnectionFailed, match="does not speak SVRnet"):
            mock(lambda request, wrong=wrong: httpx.Response(200, json=wrong)).predict([stack_file])
    late = lambda request: httpx.Response(408, json=problem(408, "no data for 60 s", "Request timeout"))  # noqa: E731
    with pytest.raises(ConnectionFailed) as e:
        mock(late).predict([stack_file])
    assert e.value.status == 408 and exit_code_for(e.value) == EXIT_CONNECTION


def test_upload_progress_reaches_the_total(stack_file: Path) -> None:
    big = stack_file.parent / "big.nii"
    big.write_bytes(bytes(range(256)) * 4000)                 # ~1 MB: several chunks
    got: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        got.append(request)
        return httpx.Response(200, json={"stacks": []})

    seen: list[tuple[int, int]] = []
    mock(handler).predict([big, stack_file], bias_correction=True, model="m", stack_consistency=True,
                          image_consistency=False, masks_hold_csf=True, progress=lambda s, t: seen.append((s, t)))
    total = len(got[0].content)
    assert len(seen) > 4 and all(t == total for _, t in seen)
    assert [s for s, _ in seen] == sorted(s for s, _ in seen) and seen[0][0] == 0 and seen[-1][0] == total
    fields, files = parse_multipart(got[0])
    assert fields == {"bias_correction": ["true"], "model": ["m"], "stack_consistency": ["true"],
                      "image_consistency": ["false"], "masks_hold_csf": ["true"]}
    assert [(f[0], f[1]) for f in files] == [("stacks", "big.nii"), ("stacks", "stack.nii.gz")]
    assert files[0][3] == big.read_bytes()


@pytest.mark.parametrize(("retry_after", "calls_made", "sleeps"), [("2", 4, [2.0, 4.0, 8.0]), ("100", 1, [])])
def test_always_busy_raises_busy(no_sleep: list[float], retry_after: str, calls_made: int,
                                 sleeps: list[float]) -> None:
    """Retry-After is honoured as the first wait, doubled at each retry and up to a quarter longer
    at random (clients refused together come back apart); a wait longer than 30 s is not shortened
    but handed to the caller, who is told how often the request was sent."""
    calls = []

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(request)
        return httpx.Response(503, headers={"Retry-After": retry_after}, json=problem(503, "saturated", "Busy"))

    with pytest.raises(Busy) as e:
        mock(handler, retries=3).models()
    assert len(calls) == calls_made and e.value.status == 503 and e.value.retry_after_s == float(retry_after)
    assert len(no_sleep) == len(sleeps) and all(s <= got <= 1.25 * s for got, s in zip(no_sleep, sleeps))
    assert "saturated" in str(e.value) and e.value.attempts == calls_made


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
    assert all(s <= got <= 1.25 * s for got, s in zip(no_sleep, [0.5, 1.0, 2.0])) and len(no_sleep) == 3
    assert e.value.status == 429 and e.value.detail == "slow down"


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
    if status == 404:                          # another web server at that URL: as if none could be reached
        assert type(plain) is ConnectionFailed and "not an SVRnet API v1 server" in plain.detail
        assert "oops" not in plain.detail and plain.request_id == "h1"
    else:
        assert type(plain) is cls and "oops" in plain.detail and plain.request_id == "h1"
    if status == 404:                          # an SVRnet server at a wrong path (a URL ending in /v1): the same
        wrong = error_from_response(httpx.Response(404, json=problem(404, "no route '/v1/v1/models': ...", "T")))
        assert type(wrong) is ConnectionFailed and exit_code_for(wrong) == EXIT_CONNECTION


def test_api_key_header_and_non_json_server_error() -> None:
    seen = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request.headers.get("authorization"))
        return httpx.Response(500, text="Internal Server Error")

    with pytest.raises(ServerError, match="Internal Server Error"):
        mock(handler, api_key="s3cret").models()
    assert seen == ["Bearer s3cret"]


# --- (c) reconstruction jobs against a fake of the contract ----------------------------------------------------


def test_a_volume_named_nii_is_written_uncompressed_and_a_cut_stream_leaves_nothing(stack_file: Path, mask_file: Path,
                                                                                     tmp_path: Path) -> None:
    """The server sends the volume gzipped; a file named ``.nii`` gets it decompressed (a viewer reads a
    ``.nii`` as plain NIfTI), one named ``.nii.gz`` as it came; a gzip stream that ends early is no file."""
    import gzip

    raw = bytes(range(256)) * 4000

    class GzippedJobs(FakeJobs):
        VOLUME = gzip.compress(raw)

    fake = GzippedJobs()
    svr = mock(fake)
    svr.reconstruct([stack_file], [mask_file])
    svr.wait("job1", poll_s=0.0)
    assert svr.download_volume("job1", tmp_path / "recon.nii").read_bytes() == raw
    assert svr.download_volume("job1", tmp_path / "recon.nii.gz").read_bytes() == GzippedJobs.VOLUME
    GzippedJobs.VOLUME = GzippedJobs.VOLUME[:-20]
    with pytest.raises(ConnectionFailed, match="ended early"):
        mock(fake, retries=0).download_volume("job1", tmp_path / "cut.nii")
    assert not (tmp_path / "cut.nii").exists() and not list(tmp_path.glob(".*part*"))

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


def test_answers_of_another_api_are_not_taken_for_a_job(stack_file: Path) -> None:
    """Valid JSON of another shape (another server or version at the URL): a failed connection that says
    so, not a job with an empty id or a table of dashes."""
    def other_api(request: httpx.Request) -> httpx.Response:
        return httpx.Response(202 if request.method == "POST" else 200, json={"id": 7, "state": "ok", "items": []})

    svr = mock(other_api)
    for call in (lambda: svr.reconstruct([stack_file]), lambda: svr.status("job1"), svr.models):
        with pytest.raises(ConnectionFailed, match="does not speak SVRnet API v1"):
            call()


def test_a_job_submission_whose_answer_is_lost_is_sent_again_with_its_key(stack_file: Path,
                                                                          no_sleep: list[float]) -> None:
    """The server answers a retry with the job the first attempt made (tests/jobs: the same key, one
    job); a new submission has a new key."""
    fake, keys = FakeJobs(), []

    losses = [httpx.ReadError("Server disconnected without sending a response"), httpx.ReadTimeout("timed out"),
              httpx.Response(502, text="<html>Bad Gateway</html>")]

    def losing_the_first_answer(request: httpx.Request) -> httpx.Response:
        answer = fake(request)
        if request.method == "POST":
            keys.append(request.headers.get("idempotency-key"))
            if len(keys) % 2:                                      # every first attempt of a submission
                lost = losses[len(keys) // 2]
                if isinstance(lost, httpx.Response):
                    return lost
                raise lost
        return answer

    svr = mock(losing_the_first_answer)
    for n in range(len(losses)):
        assert svr.reconstruct([stack_file])["job_id"]
        assert len(keys) == 2 * n + 2 and keys[-1] == keys[-2] and len(keys[-1]) >= 16
    assert len(set(keys)) == len(losses)                            # a new submission, a new key


def test_a_keyed_submission_is_sent_again_only_after_a_lost_answer_not_a_stalled_upload(
        stack_file: Path, no_sleep: list[float]) -> None:
    """A keyed submission is sent again where its answer was lost to a read timeout (the server has
    the upload and answers the retry with its job: with 3 retries, four sends), not where the upload
    itself stalled (a write timeout: sending it all again would stall again) nor where the address is
    no HTTP one; the error carries the key. An unkeyed POST is never sent again after a read timeout."""
    for raised, attempts in ((httpx.ReadTimeout, 4), (httpx.WriteTimeout, 1), (httpx.UnsupportedProtocol, 1)):
        keys: list[str] = []

        def failing(request: httpx.Request) -> httpx.Response:
            keys.append(request.headers["idempotency-key"])
            raise raised("timed out", request=request)

        with pytest.raises(ConnectionFailed) as e:
            mock(failing, retries=3).reconstruct([stack_file])
        assert len(keys) == attempts and len(set(keys)) == 1 and e.value.idempotency_key == keys[0], raised
    posts: list[str] = []

    def slow(request: httpx.Request) -> httpx.Response:
        posts.append(request.method)
        raise httpx.ReadTimeout("timed out", request=request)

    with pytest.raises(ConnectionFailed):
        mock(slow, retries=3).predict([stack_file])
    assert posts == ["POST"]


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


# --- (e) the client stays thin ------------------------------------------------------------------------------


def test_import_client_pulls_in_nothing_heavy() -> None:
    code = ("import sys, client, client.cli; "
            "bad = [m for m in sys.modules if m.split('.')[0] in "
            "('torch', 'onnxruntime', 'SimpleITK', 'numpy', 'service', 'model_export', 'scipy')]; "
            "print(','.join(sorted(bad)))")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == ""


def test_a_small_call_waits_for_a_stuck_server_no_longer_than_half_a_minute() -> None:
    """A status, the models, a cancel: SVRNET_TIMEOUT is for uploads and reconstructions on a CPU."""
    from client.multipart import MultipartBody
    from client.transport import SMALL_CALL_READ_S, Transport

    with Transport("http://svr.test", timeout=300.0) as t:
        assert t._timeout_for(None, False).read == SMALL_CALL_READ_S
        assert t._timeout_for(None, True).read == 300.0                     # a download
        assert t._timeout_for(MultipartBody({}, []), False).read == 300.0     # an upload
    with Transport("http://svr.test", timeout=5.0) as t:
        assert t._timeout_for(None, False).read == 5.0                      # never longer than asked


def test_the_server_defaults_to_svrnet_server_as_the_command_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SVRNET_SERVER", "http://recon-server:8011")
    with SVRnetClient() as svr:
        assert svr.base_url.startswith("http://recon-server:8011")
    monkeypatch.delenv("SVRNET_SERVER")
    with SVRnetClient() as svr:
        assert svr.base_url.startswith("http://127.0.0.1:8000")


def test_a_proxys_html_page_is_not_an_svrnet_answer_and_writes_no_file(tmp_path: Path) -> None:
    """A login page answered with 200: the caller is told the server is not SVRnet (exit 3), and no
    download is written from it."""
    page = lambda request: httpx.Response(200, text="<html>Please log in</html>",  # noqa: E731
                                          headers={"content-type": "text/html; charset=utf-8"})
    svr = SVRnetClient("http://svr.test", transport=httpx.MockTransport(page))
    with pytest.raises(ConnectionFailed, match="not an SVRnet server") as e:
        svr.models()
    assert exit_code_for(e.value) == EXIT_CONNECTION
    with pytest.raises(ConnectionFailed, match="text/html page, not the file"):
        svr.download_volume("job1", tmp_path / "vol.nii.gz")
    assert list(tmp_path.iterdir()) == []


# --- (f) answers lost on the way, and problem types that share a status ------------------------------------------


class _CutOff(httpx.SyncByteStream):
    """A body that ends after its first bytes, as a connection that drops mid-answer."""

    def __init__(self, head: bytes) -> None:
        self.head = head

    def __iter__(self) -> Iterator[bytes]:
        yield self.head
        raise httpx.RemoteProtocolError("peer closed connection without sending complete message body")


def test_gets_are_asked_again_after_a_proxys_502_504_or_a_cut_off_answer(tmp_path: Path,
                                                                         no_sleep: list[float]) -> None:
    fake, lost = FakeJobs(), []

    def lossy(request: httpx.Request) -> httpx.Response:
        if request.method == "GET" and lost:
            kind = lost.pop(0)
            if kind == "cut":
                return httpx.Response(200, headers={"content-length": "4000"}, stream=_CutOff(b"\x1f\x8b cut"))
            return httpx.Response(kind, text="<html>Bad Gateway</html>")
        return fake(request)

    svr = mock(lossy, retries=3)
    job_id = svr.reconstruct([__file__])["job_id"]
    lost[:] = [502, 504, "cut"]
    assert svr.status(job_id)["job_id"] == job_id and lost == [] and len(no_sleep) == 3
    svr.wait(job_id, poll_s=0.0)
    lost[:] = ["cut", 502]
    out = svr.download_volume(job_id, tmp_path / "vol.nii.gz")
    assert out.read_bytes() == FakeJobs.VOLUME and sorted(p.name for p in tmp_path.iterdir()) == ["vol.nii.gz"]
    lost[:] = ["cut"] * 4                                      # cut off every time: no half-written file
    with pytest.raises(ConnectionFailed, match="RemoteProtocolError"):
        svr.download_volume(job_id, tmp_path / "again.nii.gz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["vol.nii.gz"]


def test_a_post_is_not_sent_again_after_a_502(stack_file: Path) -> None:
    calls = []

    def gateway(request: httpx.Request) -> httpx.Response:
        calls.append(request.method)
        return httpx.Response(502, text="<html>Bad Gateway</html>")

    with pytest.raises(ServerError):
        mock(gateway, retries=3).predict([stack_file])
    assert calls == ["POST"]                                   # /v1/predict may have run: not repeated unasked


@pytest.mark.parametrize(("status", "ptype", "cls", "code"), [
    (422, "/problems/idempotency-key-reused", KeyReused, 10),
    (422, "/problems/unusable-image", UnusableInput, 5),
    (403, "/problems/origin-not-allowed", OriginNotAllowed, 4),
    (403, "/problems/unauthorized", Unauthorized, 4),
    (400, "/problems/idempotency-key-reused", BadRequest, 5),   # a type the status does not agree with
])
def test_problem_types_that_share_a_status_are_told_apart(status: int, ptype: str, cls: type[SVRnetError],
                                                          code: int) -> None:
    err = error_from_response(httpx.Response(status, json={**problem(status, "x"), "type": ptype}))
    assert type(err) is cls and exit_code_for(err) == code
    streamed = client_stream._server_error({"type": "error", "status": status, "problem_type": ptype, "detail": "x"})
    assert type(streamed) is cls


def test_the_cli_names_the_origin_not_the_key(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(typer.Exit) as e, errors():
        raise error_from_response(httpx.Response(403, json={**problem(403, "Origin: not allowed"),
                                                            "type": "/problems/origin-not-allowed"}))
    said = capsys.readouterr().err
    assert e.value.exit_code == 4 and "SVRNET_ALLOWED_ORIGINS" in said and "API_KEY" not in said
    with pytest.raises(typer.Exit) as e, errors():
        raise KeyboardInterrupt
    assert e.value.exit_code == EXIT_INTERRUPTED and "130 interrupted" in EXIT_HELP


def test_a_keyed_submission_that_stays_busy_names_its_key_and_a_rerun_sends_it(stack_file: Path,
                                                                               no_sleep: list[float]) -> None:
    """A submission whose answer the server kept busy (its first copy may be queued, still being read)
    raises Busy naming the key it was sent with; the same request with that key sends it again, so
    the server answers with the first one's job, not a second."""
    keys: list[str] = []

    def busy(request: httpx.Request) -> httpx.Response:
        keys.append(request.headers["idempotency-key"])
        return httpx.Response(503, headers={"Retry-After": "1"},
                              json=problem(503, "Idempotency-Key: the first submission with this key is still being read"))

    with pytest.raises(Busy) as e:
        mock(busy, retries=2).reconstruct([stack_file])
    assert len(set(keys)) == 1 and len(keys) == 3
    assert f"idempotency key {keys[0]}" in str(e.value) and "send it again with that key" in str(e.value)

    def made(request: httpx.Request) -> httpx.Response:
        keys.append(request.headers["idempotency-key"])
        return httpx.Response(202, json={"job_id": "j1", "status": "queued", "status_url": "/v1/reconstructions/j1"})

    assert mock(made).reconstruct([stack_file], idempotency_key=keys[0])["job_id"] == "j1" and keys[-1] == keys[0]



def test_a_submission_whose_answer_is_lost_names_its_key_and_a_refused_one_carries_it_quietly(
        stack_file: Path, no_sleep: list[float]) -> None:
    """The connection dropped after the upload (the server may have made the job), or a gateway's 502
    after the retries: the error names the key and carries it, so that a rerun with it gets that job;
    a server never reached, or a 400, made no job: the key is carried but not offered."""
    keys: list[str] = []

    def drop(request: httpx.Request) -> httpx.Response:
        keys.append(request.headers["idempotency-key"])
        request.read()
        raise httpx.RemoteProtocolError("Server disconnected without sending a response.", request=request)

    def gateway(request: httpx.Request) -> httpx.Response:
        keys.append(request.headers["idempotency-key"])
        return httpx.Response(502, text="bad gateway")

    for handler, kind in ((drop, ConnectionFailed), (gateway, ServerError)):
        keys.clear()
        with pytest.raises(kind) as e:
            mock(handler, retries=1).reconstruct([stack_file])
        assert len(keys) == 2 and len(set(keys)) == 1 and e.value.idempotency_key == keys[0]
        assert f"idempotency key {keys[0]}: the server may hold its job" in str(e.value)

    def unreachable(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("Connection refused", request=request)

    with pytest.raises(ConnectionFailed) as e:                   # nothing reached the server: no job to get
        mock(unreachable, retries=0).reconstruct([stack_file], idempotency_key="u" * 20)
    assert e.value.idempotency_key == "u" * 20 and "may hold" not in str(e.value)

    def refused(request: httpx.Request) -> httpx.Response:
        return httpx.Response(400, json=problem(400, "resolution_mm: at most 5"))

    with pytest.raises(BadRequest) as e:
        mock(refused).reconstruct([stack_file], idempotency_key="k" * 20)
    assert e.value.idempotency_key == "k" * 20 and "may hold" not in str(e.value)

@pytest.fixture
def https_server(tmp_path: Path):  # noqa: ANN201
    """An HTTPS server on 127.0.0.1 with a self-signed certificate (a site's own CA): its URL and the
    certificate's path."""
    import http.server
    import ssl
    import threading

    from tests.support.certificates import self_signed

    cert, key = self_signed(tmp_path)

    class Health(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - the standard library's name
            send_json(self, {"status": "ok"})

        def log_message(self, *args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Health)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(cert, key)
    server.socket = context.wrap_socket(server.socket, server_side=True)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"https://127.0.0.1:{server.server_address[1]}", cert
    finally:
        server.shutdown()


def test_a_server_certificate_of_a_sites_own_ca_is_trusted_where_its_bundle_is_given(
        https_server, monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: ANN001
    """Unknown to this machine, the certificate is refused with advice that keeps TLS (never "use
    http://", which would send the API key in the clear); the site's CA bundle, by SVRNET_CA_BUNDLE or
    ``verify=``, makes the server answer; a bundle that is not there is a usage error."""
    url, cert = https_server
    monkeypatch.delenv("SVRNET_CA_BUNDLE", raising=False)
    with pytest.raises(ConnectionFailed, match="not one this client trusts: give your site's CA bundle") as refused:
        SVRnetClient(url, retries=0).health()
    assert "does not speak TLS" not in str(refused.value)
    assert SVRnetClient(url, verify=str(cert)).health() == {"status": "ok"}
    monkeypatch.setenv("SVRNET_CA_BUNDLE", str(cert))
    assert SVRnetClient(url).health() == {"status": "ok"}
    monkeypatch.setenv("SVRNET_CA_BUNDLE", str(cert.with_name("missing.pem")))
    with pytest.raises(ArgumentError, match="missing.pem .SVRNET_CA_BUNDLE or verify=. is not a file"):
        SVRnetClient(url)
