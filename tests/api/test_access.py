"""Who may call the service: the owner a job is kept under, and keys presented both ways."""

from __future__ import annotations

from starlette.datastructures import Headers

from service.api.access import api_key_ok, job_owner, key_owner
from service.core.settings import Settings


def test_a_job_belongs_to_the_digest_of_the_key_that_made_it_and_to_no_one_without_keys() -> None:
    keyed = Settings(api_keys="k-1,k-2")
    by_bearer = job_owner(keyed, Headers({"authorization": "Bearer k-1"}))
    by_header = job_owner(keyed, Headers({"x-api-key": "k-1"}))
    assert by_bearer == by_header == key_owner("k-1") and "k-1" not in by_bearer
    assert job_owner(keyed, Headers({"x-api-key": "k-2"})) != by_bearer
    assert job_owner(Settings(), Headers({"x-api-key": "k-1"})) is None


def test_a_bearer_token_is_read_before_the_x_api_key_header() -> None:
    assert api_key_ok({"k-1"}, "Bearer k-1", "wrong") and not api_key_ok({"k-1"}, "Bearer wrong", "k-1")


def test_a_listed_origins_page_may_read_the_answers_and_no_other_origin_gains_anything(
        phantom_files) -> None:  # noqa: ANN001
    """A viewer page of a listed origin gets its preflight answered (no key with it, as browsers send
    none) and every answer marked readable by it, errors included; a page of another origin gets no
    CORS header and the service's own refusal (401 without a key, 403 without keys set)."""
    from service.inference.registry import ModelRegistry
    from tests.api.conftest import OracleEstimator, make_client

    viewer, evil, key = "https://viewer.example", "https://evil.example", "k" * 24
    preflight = {"access-control-request-method": "POST", "access-control-request-headers": "x-api-key"}
    stack, mask, _ = phantom_files
    files = [("stacks", (stack.name, stack.read_bytes())), ("masks", (mask.name, mask.read_bytes()))]
    with make_client(ModelRegistry({"default": OracleEstimator()}), api_keys=key, allowed_origins=viewer) as client:
        ok = client.options("/v1/predict", headers={"origin": viewer, **preflight})
        assert ok.status_code == 200 and ok.headers["access-control-allow-origin"] == viewer
        assert "x-api-key" in ok.headers["access-control-allow-headers"].lower()
        answered = client.get("/v1/models", headers={"origin": viewer, "x-api-key": key})
        assert answered.status_code == 200 and answered.headers["access-control-allow-origin"] == viewer
        assert "x-request-id" in answered.headers["access-control-expose-headers"].lower()
        keyless = client.post("/v1/predict", files=files, headers={"origin": viewer})
        assert keyless.status_code == 401 and keyless.headers["access-control-allow-origin"] == viewer
        other = client.options("/v1/predict", headers={"origin": evil, **preflight})
        assert other.status_code == 401 and "access-control-allow-origin" not in other.headers
    with make_client(ModelRegistry({"default": OracleEstimator()}), allowed_origins=viewer) as client:
        other = client.post("/v1/predict", files=files, headers={"origin": evil})
        assert other.status_code == 403 and "access-control-allow-origin" not in other.headers
