"""Operations: models, health, readiness, metrics, API keys, request ids, saturation, logs, real model."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import numpy as np
from fastapi.testclient import TestClient

from service.core.logging import JsonFormatter
from service.core.settings import Settings
from service.inference.estimator import OnnxPoseEstimator
from service.inference.model_file import load_model
from service.inference.registry import ModelRegistry
from service.io.volume import Volume, write_volume
from service.main import create_app
from tests.api.conftest import make_client
from tests.support.local_client import LocalClient


def upload(client: TestClient, stack: Path, mask: Path | None, **data: str):  # noqa: ANN201
    files = [("stacks", (stack.name, stack.read_bytes()))]
    if mask is not None:
        files.append(("masks", (mask.name, mask.read_bytes())))
    return client.post("/v1/predict", files=files, data=data)


def test_real_exported_model_through_the_whole_path(real_client: TestClient, phantom_files) -> None:
    stack, mask, n = phantom_files
    r = upload(real_client, stack, mask, mc_samples="20")
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["model"]["name"] == "default" and body["model"]["backbone"] == "compact"
    assert body["mc_samples"] == 20 and len(body["model"]["sha256"]) == 64
    slices = body["stacks"][0]["slices"]
    assert len(slices) == n
    for s in slices:
        r_ = np.array(s["rotation"])
        np.testing.assert_allclose(r_ @ r_.T, np.eye(3), atol=1e-9)
        assert s["geodesic_variance"] > 0  # real MC dropout: samples differ
        assert np.array(s["atlas_from_voxel"]).shape == (4, 4) and len(s["quaternion_wxyz"]) == 4
        assert (s["reason"] is None) == s["accepted"]
    assert set(body["timing_ms"]) >= {"read", "preprocess", "inference", "statistics", "total"}
    # N4 on (default) and off give results for the same slices.
    r2 = upload(real_client, stack, mask, mc_samples="5", bias_correction="false")
    assert r2.status_code == 200 and len(r2.json()["stacks"][0]["slices"]) == n
    # The model's fixed draws: the same request, the same answer.
    again = upload(real_client, stack, mask, mc_samples="20").json()["stacks"][0]["slices"]
    assert [(s["rotation"], s["translation_mm"], s["expected_error_mm"], s["accepted"]) for s in again] == \
        [(s["rotation"], s["translation_mm"], s["expected_error_mm"], s["accepted"]) for s in slices]


def test_models_health_ready_metrics(real_client: TestClient, phantom_files) -> None:
    models = real_client.get("/v1/models").json()
    assert models[0]["name"] == "default" and models[0]["input_size"] == 64 and models[0]["label_type"] == "anchor"
    assert set(models[0]) >= {"name", "version", "backbone", "sha256", "input_size", "spacing_mm", "label_type",
                              "variance_threshold", "trained_on"}
    assert models[0]["mc_seed"] == 0                                   # the tiny model's fixed draws
    assert real_client.get("/healthz").json() == {"status": "ok"}
    ready = real_client.get("/readyz")
    assert ready.status_code == 200 and ready.json()["workers"] == real_client.app.state.job_runner.live_workers() >= 1
    upload(real_client, *phantom_files[:2], mc_samples="2")
    text = real_client.get("/metrics").text
    assert 'svrnet_requests_total{method="POST",model="default",route="/v1/predict",status="200"}' in text
    assert "svrnet_slices_processed_total" in text and "svrnet_request_seconds_bucket" in text
    assert real_client.get("/openapi.json").json()["paths"]["/v1/predict"]["post"]


def test_readyz_is_503_without_models() -> None:
    with make_client(ModelRegistry({})) as client:
        r = client.get("/readyz")
    assert r.status_code == 503 and r.headers["retry-after"]



def test_a_scratch_folder_that_cannot_take_uploads_makes_the_server_unready_and_uploads_a_503(
        oracle, phantom_files, tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    """``SVRNET_TMP_DIR`` gone (or read-only) after the start, or its disk full: ``/readyz`` is 503 naming
    it, so that a load balancer stops sending uploads; an upload sent all the same is a 503 (the
    server's fault), not a 500; once the folder takes uploads again, both recover."""
    import shutil

    from service.api import uploads

    scratch = tmp_path / "scratch"
    scratch.mkdir()
    with make_client(ModelRegistry({"default": oracle}), tmp_dir=scratch) as client:
        assert client.get("/readyz").status_code == 200
        scratch.rmdir()
        r = client.get("/readyz")
        assert r.status_code == 503 and "SVRNET_TMP_DIR" in r.json()["detail"] and r.headers["retry-after"]
        sent = upload(client, *phantom_files[:2])
        assert sent.status_code == 503 and "scratch folder" in sent.json()["detail"], sent.text
        scratch.mkdir()
        assert client.get("/readyz").status_code == 200
        monkeypatch.setattr(uploads.shutil, "disk_usage",
                            lambda path: shutil._ntuple_diskusage(10 << 30, 10 << 30, 1 << 20))   # 1 MB free
        assert client.get("/readyz").status_code == 503

def test_a_job_store_that_hangs_is_reported_down_without_waiting_for_it(oracle, monkeypatch) -> None:  # noqa: ANN001
    """A store that takes the question and answers nothing (a hung Redis costs each question its 10 s
    socket timeout): ``/readyz`` answers 503 naming the wait, and ``/metrics`` reports the store down,
    while its question is still unanswered; once the store answers, both see it up again."""
    import threading
    import time

    from service.jobs import store_probe

    monkeypatch.setattr(store_probe, "PROBE_WAIT_S", 0.2)
    with make_client(ModelRegistry({"default": oracle})) as client:
        store = client.app.state.job_store
        answering, release = store.ping, threading.Event()
        monkeypatch.setattr(store, "ping", lambda: release.wait(60) and answering())
        try:
            r = client.get("/readyz")
            assert r.status_code == 503 and "did not answer within 0.2 s" in r.json()["detail"], r.text
            assert "svrnet_job_store_up 0.0" in client.get("/metrics").text
            assert client.get("/readyz").status_code == 503              # the same question, still unanswered
        finally:
            release.set()
        for _ in range(100):
            if client.get("/readyz").status_code == 200 and "svrnet_job_store_up 1.0" in client.get("/metrics").text:
                break
            time.sleep(0.05)
        else:
            raise AssertionError("the store answers again and is not seen up")


def test_api_keys(tiny_model_path: Path, phantom_files) -> None:
    registry = ModelRegistry({"default": OnnxPoseEstimator(load_model(tiny_model_path))})
    with make_client(registry, api_keys="k1,k2") as client:
        assert client.get("/v1/models").status_code == 401
        assert client.get("/v1/models", headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert client.get("/v1/models", headers={"Authorization": "Bearer k2"}).status_code == 200
        assert client.get("/v1/models", headers={"X-API-Key": "k1"}).status_code == 200
        for odd in ("caf\xe9".encode("latin-1"), b"\xff\xfe"):                # bytes no ASCII key holds: 401, not 500
            assert client.get("/v1/models", headers={"X-API-Key": odd}).status_code == 401
            assert client.get("/v1/models", headers={"Authorization": b"Bearer " + odd}).status_code == 401
        assert client.get("/healthz").status_code == 200          # liveness stays open
        r = client.post("/v1/predict", files=[("stacks", ("s.nii.gz", phantom_files[0].read_bytes()))])
        assert r.status_code == 401 and r.headers["content-type"].startswith("application/problem+json")


def test_another_site_s_page_is_refused_without_keys(tiny_model_path: Path, phantom_files) -> None:
    """A browser page of another origin posts a form without any CORS permission: refused (403) before
    its upload is read, unless listed; so is a page whose DNS name was rebound to the server, even
    where its same-origin GET carries neither Origin nor Sec-Fetch-Site (Chromium sends none to a
    plain-HTTP name: it was served); the server's own page at its address, an address the user typed,
    and scripts at an address or a listed name, are served."""
    registry = ModelRegistry({"default": OnnxPoseEstimator(load_model(tiny_model_path))})
    stack = [("stacks", ("s.nii.gz", phantom_files[0].read_bytes()))]
    with make_client(registry, allowed_origins="https://viewer.example/") as client:
        evil = {"Origin": "https://evil.example"}
        r = client.post("/v1/predict", files=stack, headers=evil)
        assert r.status_code == 403 and r.json()["type"] == "/problems/origin-not-allowed"
        assert "SVRNET_ALLOWED_ORIGINS" in r.json()["detail"]
        assert client.get("/v1/models", headers={"Origin": "null"}).status_code == 403
        rebound = {"Host": "evil.example:8000", "Origin": "http://evil.example:8000"}    # DNS rebinding
        assert client.get("/v1/models", headers=rebound).status_code == 403
        page = {"Host": "evil.example:8000", "Sec-Fetch-Site": "same-origin"}    # a rebound page's GET: no Origin
        assert client.get("/v1/models", headers=page).status_code == 403
        assert client.get("/v1/models", headers={**page, "Host": "127.0.0.1:8000"}).status_code == 200
        assert client.get("/v1/models", headers={**page, "Sec-Fetch-Site": "none"}).status_code == 200   # typed
        own = {"Host": "127.0.0.1:8000", "Origin": "http://127.0.0.1:8000"}
        assert client.get("/v1/models", headers=own).status_code == 200
        assert client.get("/v1/models", headers={"Origin": "https://Viewer.example"}).status_code == 200
        assert client.get("/v1/models", headers={"Origin": "https://viewer.example:443"}).status_code == 200
        assert client.get("/healthz", headers=evil).status_code == 200          # probes and docs stay open
        assert client.get("/v1/models").status_code == 200
        # A page at a plain-HTTP name gets no Sec-Fetch-Site from the browser: its GET looks like a
        # script's, and a script's at a name is refused unless the name is listed.
        r = client.get("/v1/models", headers={"Host": "evil.example:8000"})
        assert r.status_code == 403 and r.json()["detail"].startswith("Host: ") and "SVRNET_ALLOWED_ORIGINS" in r.json()["detail"]
        assert client.get("/v1/models", headers={"Host": "viewer.example"}).status_code == 200     # listed
        assert client.get("/healthz", headers={"Host": "evil.example:8000"}).status_code == 200
    with make_client(registry, api_keys="k1") as client:                    # with keys, the key decides
        assert client.get("/v1/models", headers={"Origin": "https://evil.example", "X-API-Key": "k1"}).status_code == 200
        assert client.get("/v1/models", headers={"Host": "svr-box:8000", "X-API-Key": "k1"}).status_code == 200


def test_request_id_is_returned_and_kept(real_client: TestClient) -> None:
    r = real_client.get("/healthz", headers={"X-Request-ID": "abc-123"})
    assert r.headers["x-request-id"] == "abc-123"
    r = real_client.get("/healthz", headers={"X-Request-ID": "bad id with spaces"})
    assert r.headers["x-request-id"] != "bad id with spaces" and len(r.headers["x-request-id"]) == 32


def test_saturation_answers_503_with_retry_after(oracle, phantom_files) -> None:
    with make_client(ModelRegistry({"default": oracle}), max_concurrent=1, retry_after_s=7, slot_wait_s=0.1) as client:
        sem: asyncio.Semaphore = client.app.state.slots
        sem._value = 0  # all slots taken by other requests
        r = upload(client, *phantom_files[:2])
        assert r.status_code == 503 and r.headers["retry-after"] == "7"


def test_logs_never_contain_file_names(real_client: TestClient, phantom_files, caplog, tmp_path: Path) -> None:
    secret = tmp_path / "Doe_Jane_19840101.nii.gz"
    secret.write_bytes(phantom_files[0].read_bytes())
    with caplog.at_level(logging.DEBUG, logger="service"):
        upload(real_client, secret, phantom_files[1], mc_samples="2")
        real_client.post("/v1/predict", files=[("stacks", ("Doe_Jane_19840101.nii.gz", b"garbage"))])
    lines = [JsonFormatter().format(r) for r in caplog.records]
    assert lines and not any("Doe" in line for line in lines)


def _call_without_reading_the_body(app, path: str, headers: list) -> tuple[int, dict, bool]:  # noqa: ANN001
    """Drive the ASGI app by hand: the answer's status and headers, and whether the body was read."""
    read = {"body": False}
    answer: dict = {}

    async def receive() -> dict:
        read["body"] = True
        return {"type": "http.request", "body": b"x" * 1000, "more_body": False}

    async def send(message: dict) -> None:
        if message["type"] == "http.response.start":
            answer["status"] = message["status"]
            answer["headers"] = {k.decode(): v.decode() for k, v in message["headers"]}

    scope = {"type": "http", "method": "POST", "path": path, "raw_path": path.encode(), "query_string": b"",
             "headers": [(b"content-type", b"multipart/form-data; boundary=xx"), *headers], "app": app,
             "root_path": "", "scheme": "http", "server": ("test", 80), "client": ("test", 1)}
    asyncio.run(app(scope, receive, send))
    return answer["status"], answer["headers"], read["body"]


def test_refusals_come_before_the_upload_is_read(oracle) -> None:
    """No key, or a saturated server: the client is answered before it has pushed its stacks."""
    with make_client(ModelRegistry({"default": oracle}), api_keys="k1", max_concurrent=1, retry_after_s=5) as client:
        app = client.app
        status, headers, read = _call_without_reading_the_body(app, "/v1/predict", [])
        assert (status, read) == (401, False) and headers["x-request-id"]
        status, _, read = _call_without_reading_the_body(app, "/v1/reconstructions", [(b"x-api-key", b"wrong")])
        assert (status, read) == (401, False)
        app.state.admissions._value = 0
        status, headers, read = _call_without_reading_the_body(app, "/v1/predict", [(b"authorization", b"Bearer k1")])
        assert (status, read, headers["retry-after"]) == (503, False, "5")


def test_model_default_means_the_configured_default(tiny_model_path: Path, phantom_files, tmp_path: Path) -> None:
    """SVRNET_DEFAULT_MODEL=v7 with only ``<models_dir>/v7/model.onnx``: ``model=default`` is v7."""
    (tmp_path / "models" / "v7").mkdir(parents=True)
    (tmp_path / "models" / "v7" / "model.onnx").symlink_to(tiny_model_path)
    with LocalClient(create_app(Settings(models_dir=tmp_path / "models", default_model="v7",
                                        data_dir=tmp_path / "jobs"))) as client:
        r = upload(client, phantom_files[0], phantom_files[1], mc_samples="2")
        assert r.status_code == 200 and r.json()["model"]["name"] == "v7", r.text
        r = client.post("/v1/predict", files=[("stacks", ("s.nii.gz", b"x"))], data={"model": "v8"})
        assert r.status_code == 404 and "v8" in r.json()["detail"]


def test_openapi_documents_errors_as_the_handlers_answer_them(oracle) -> None:
    with make_client(ModelRegistry({"default": oracle})) as client:
        spec = client.get("/openapi.json").json()
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            responses = op["responses"]
            if path.startswith("/v1/"):
                assert "401" in responses, (method, path)
            for code, response in responses.items():
                assert response.get("description") != "Validation Error", (method, path)
                if code[0] in "45":
                    assert list(response["content"]) == ["application/problem+json"], (method, path, code)
    assert "422" in spec["paths"]["/v1/predict"]["post"]["responses"]       # unusable images


def test_a_slice_without_brain_gets_no_network_pose(real_client: TestClient, phantom_files, tmp_path: Path) -> None:
    """A slice whose mask is empty is ``empty``, has no network pose or variance (``null``), and still
    gets its stack model's pose; the slices with brain keep finite ones."""
    from service.io.volume import read_volume

    stack, mask, n = phantom_files
    m = read_volume(mask)
    cut = np.asarray(m.array).copy()
    cut[..., :3] = 0
    write_volume(Volume(cut, m.affine), tmp_path / "cut.nii.gz")
    r = upload(real_client, stack, tmp_path / "cut.nii.gz", mc_samples="20")
    assert r.status_code == 200, r.text
    slices = r.json()["stacks"][0]["slices"]
    assert len(slices) == n
    for s in slices[:3]:
        assert s["reason"] == "empty" and s["geodesic_variance"] is None and s["network_atlas_from_voxel"] is None
        assert np.isfinite(np.array(s["atlas_from_voxel"])).all()
    for s in slices[3:]:
        assert s["geodesic_variance"] > 0 and s["network_atlas_from_voxel"] is not None


def test_the_shipped_models_and_localisers_say_their_licences_cards_and_which_localiser_is_the_default() -> None:
    """An operator sees what the server serves: each pose model's and localiser's licences (the CRL
    atlas's non-commercial use, inherited), whether its card is in its folder, and the localiser that
    stacks without masks go to."""
    with LocalClient(create_app(Settings()), base_url="http://127.0.0.1") as client:
        models = client.get("/v1/models").json()
        localisers = client.get("/v1/localisers").json()
    assert {m["name"] for m in models} >= {"default", "fast"}
    assert all("non-commercial" in m["licences"] and m["card"] for m in models), models
    assert [loc["name"] for loc in localisers if loc["default"]] == ["default"]
    shipped = next(loc for loc in localisers if loc["name"] == "default")
    assert shipped["card"] and "non-commercial" in shipped["licences"] and len(shipped["sha256"]) == 64
