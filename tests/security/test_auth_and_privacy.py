"""The auth matrix (every documented route x no key / wrong key / right key) and privacy probes: a job
made from a DICOM series with a patient name leaves no trace of it on disk once it has ended."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.inference.registry import ModelRegistry
from tests.support import corpus
from tests.api.conftest import OracleEstimator, make_client

OPEN = {"/healthz", "/readyz", "/openapi.json", "/docs", "/redoc", "/docs/oauth2-redirect"}


@pytest.fixture(scope="module")
def keyed(tmp_path_factory: pytest.TempPathFactory):  # noqa: ANN201
    with make_client(ModelRegistry({"default": OracleEstimator()}), api_keys="k1,k2",
                     data_dir=str(tmp_path_factory.mktemp("auth"))) as client:
        yield client


def _routes(client: TestClient) -> list[tuple[str, str]]:
    spec = client.get("/openapi.json").json()
    return [(m.upper(), p.replace("{job_id}", "0" * 32)) for p, ops in spec["paths"].items() for m in ops]


@pytest.mark.parametrize("key", [None, {"Authorization": "Bearer nope"}, {"X-API-Key": ""}, {"Authorization": "k1"},
                                 {"X-API-Key": "k1 "}, {"Authorization": "Basic azE6"}])
def test_every_protected_route_refuses_a_missing_or_wrong_key(keyed: TestClient, key: dict | None) -> None:
    routes = _routes(keyed)
    assert ("GET", "/metrics") in routes and len(routes) >= 9
    for method, path in routes:
        r = keyed.request(method, path, headers=key or {})
        if path in OPEN:
            assert r.status_code == 200, (method, path)
        else:
            assert r.status_code == 401, (method, path, r.status_code)
            assert r.headers["www-authenticate"] == "Bearer" and "svrnet_" not in r.text


def test_the_right_key_opens_every_route(keyed: TestClient) -> None:
    for method, path in _routes(keyed):
        for header in ({"Authorization": "Bearer k2"}, {"X-API-Key": "k1"}):
            r = keyed.request(method, path, headers=header)
            assert r.status_code not in (401, 403, 500), (method, path, r.status_code)


def test_a_finished_job_leaves_no_patient_data_on_disk(tmp_path: Path) -> None:
    planes = [(np.random.default_rng(k).random((24, 24)) * 500).astype(np.uint16) for k in range(6)]
    series = corpus.zipped({f"IM{k}": corpus.dicom(p, k) for k, p in enumerate(planes)})
    assert b"Doe^Jane" in corpus.dicom(planes[0])
    with make_client(ModelRegistry({"default": OracleEstimator()}), data_dir=str(tmp_path)) as client:
        r = client.post("/v1/reconstructions", files=[("stacks", ("Doe_Jane_T2.zip", series))],
                        data={"resolution_mm": "3.0", "svr_iterations": "0", "mc_samples": "2"})
        assert r.status_code == 202, r.text
        job_id = r.json()["job_id"]
        for _ in range(600):
            if client.get(f"/v1/reconstructions/{job_id}").json()["status"] in ("succeeded", "failed"):
                break
            time.sleep(0.2)
        st = client.get(f"/v1/reconstructions/{job_id}").json()
    assert st["status"] in ("succeeded", "failed"), st
    for p in tmp_path.rglob("*"):
        if p.is_file():
            data = p.read_bytes()
            assert b"Doe" not in data and b"P-19840101" not in data, p
