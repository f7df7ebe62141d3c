"""With API keys configured, ``/metrics`` needs a key too, unless SVRNET_METRICS_PUBLIC says so."""

from __future__ import annotations

from service.inference.registry import ModelRegistry
from tests.api.conftest import make_client


def test_metrics_need_a_key_when_keys_are_configured(oracle) -> None:  # noqa: ANN001
    with make_client(ModelRegistry({"default": oracle}), api_keys="k1") as client:
        r = client.get("/metrics")
        assert r.status_code == 401 and r.headers["content-type"].startswith("application/problem+json")
        assert "svrnet_requests_total" not in r.text
        assert client.get("/metrics", headers={"Authorization": "Bearer wrong"}).status_code == 401
        ok = client.get("/metrics", headers={"X-API-Key": "k1"})
        assert ok.status_code == 200 and "svrnet_requests_total" in ok.text
        assert client.get("/healthz").status_code == 200 and client.get("/readyz").status_code == 200


def test_metrics_public_is_an_explicit_choice(oracle) -> None:  # noqa: ANN001
    with make_client(ModelRegistry({"default": oracle}), api_keys="k1", metrics_public=True) as client:
        assert client.get("/metrics").status_code == 200
        assert client.get("/v1/models").status_code == 401          # the rest stays protected
    with make_client(ModelRegistry({"default": oracle})) as client:   # no keys: nothing to protect with
        assert client.get("/metrics").status_code == 200


def test_openapi_says_metrics_may_answer_401(oracle) -> None:  # noqa: ANN001
    with make_client(ModelRegistry({"default": oracle}), api_keys="k1") as client:
        spec = client.get("/openapi.json").json()
    assert "401" in spec["paths"]["/metrics"]["get"]["responses"]
