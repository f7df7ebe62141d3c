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


def test_labels_stay_bounded_and_early_refusals_name_their_route(oracle) -> None:  # noqa: ANN001
    """An invented HTTP method is ``other`` (one series, not one per token a client makes up), and an
    answer given before routing (a refused key) is counted under the route the path matches."""
    with make_client(ModelRegistry({"default": oracle}), api_keys="k1", metrics_public=True) as client:
        for method in ("JANEDOE", "XYZZY"):
            client.request(method, "/healthz")
        assert client.get("/v1/models").status_code == 401
        assert client.get("/v1/reconstructions/0123456789abcdef0123456789abcdef").status_code == 401
        lines = [x for x in client.get("/metrics").text.splitlines() if x.startswith("svrnet_requests_total{")]
    assert not any("JANEDOE" in x or "XYZZY" in x for x in lines)
    assert any('method="other"' in x and 'route="/healthz"' in x for x in lines), lines
    assert any('route="/v1/models"' in x and 'status="401"' in x for x in lines), lines
    assert any('route="/v1/reconstructions/{job_id}"' in x and 'status="401"' in x for x in lines), lines


def test_stream_sessions_and_the_job_store_are_watched(oracle) -> None:  # noqa: ANN001
    with make_client(ModelRegistry({"default": oracle})) as client:
        text = client.get("/metrics").text
        assert "svrnet_stream_sessions 0.0" in text and "svrnet_job_store_up 1.0" in text
        client.app.state.stream_sessions = 2
        client.app.state.job_store.db_path = client.app.state.job_store.data_dir / "jobs"   # no database opens there
        text = client.get("/metrics").text
    assert "svrnet_stream_sessions 2.0" in text and "svrnet_job_store_up 0.0" in text


def test_the_model_label_is_the_model_a_submission_named(oracle, phantom_files) -> None:  # noqa: ANN001
    """A job's submission is counted under its pose model once its form is read, as a prediction is;
    one whose form cannot be read, under none."""
    stack, _, _ = phantom_files
    with make_client(ModelRegistry({"default": oracle})) as client:
        with stack.open("rb") as f:
            refused = client.post("/v1/reconstructions", files=[("stacks", ("s.nii.gz", f.read()))],
                                  headers=[("Idempotency-Key", "a" * 16), ("Idempotency-Key", "b" * 16)])
        assert refused.status_code == 400                   # refused after its model was resolved
        assert client.post("/v1/reconstructions", data={"resolution_mm": "x"}).status_code in (400, 422)
        lines = [x for x in client.get("/metrics").text.splitlines() if x.startswith("svrnet_requests_total{")]
    assert any('model="default"' in x and 'route="/v1/reconstructions"' in x and 'status="400"' in x
               for x in lines), lines
    assert any('model=""' in x and 'route="/v1/reconstructions"' in x and 'status="4' in x for x in lines), lines
