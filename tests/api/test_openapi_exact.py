"""The OpenAPI page says exactly what the server does (methods, Allow, list sizes, fields)."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from service.inference.registry import ModelRegistry
from tests.api.conftest import make_client


def _body_schema(spec: dict, path: str) -> dict:
    ref = spec["paths"][path]["post"]["requestBody"]["content"]["multipart/form-data"]["schema"]["$ref"]
    return spec["components"]["schemas"][ref.rsplit("/", 1)[1]]


@pytest.mark.parametrize("max_files", [32, 5])
def test_stacks_and_masks_carry_their_limits(oracle, max_files: int) -> None:  # noqa: ANN001
    with make_client(ModelRegistry({"default": oracle}), max_files=max_files) as client:
        spec = client.get("/openapi.json").json()
    for path in ("/v1/predict", "/v1/reconstructions"):
        props = _body_schema(spec, path)["properties"]
        assert (props["stacks"]["minItems"], props["stacks"]["maxItems"]) == (1, max_files), path
        assert props["masks"]["maxItems"] == max_files, path
        assert not [n for n, p in props.items() if {"type": "null"} in p.get("anyOf", [])], props
    masks_route = _body_schema(spec, "/v1/masks")["properties"]
    assert (masks_route["stacks"]["minItems"], masks_route["stacks"]["maxItems"]) == (1, max_files)
    assert set(masks_route) == {"stacks", "model", "margin_mm"}
    assert (masks_route["margin_mm"]["minimum"], masks_route["margin_mm"]["maximum"]) == (0.0, 20.0)
    assert "poses" in _body_schema(spec, "/v1/reconstructions")["properties"]
    assert _body_schema(spec, "/v1/predict")["additionalProperties"] is False


@pytest.mark.parametrize(("path", "declared"), [("/v1/reconstructions/abc", {"GET", "DELETE"}),
                                                ("/v1/reconstructions", {"POST"}), ("/v1/predict", {"POST"}),
                                                ("/v1/masks", {"POST"}),
                                                ("/v1/reconstructions/abc/volume", {"GET"})])
def test_allow_lists_every_method_of_the_path(oracle_client: TestClient, path: str, declared: set[str]) -> None:
    options = oracle_client.options(path)
    assert options.status_code == 204
    allow = {m.strip() for m in options.headers["allow"].split(",")}
    assert allow - {"HEAD", "OPTIONS"} == declared, allow
    r = oracle_client.request("PATCH", path)
    assert r.status_code == 405 and r.headers["content-type"].startswith("application/problem+json")
    assert {m.strip() for m in r.headers["allow"].split(",")} == allow


def test_head_is_answered_wherever_allow_lists_it_as_get_is_without_the_body(oracle_client: TestClient) -> None:
    """``Allow`` names HEAD with every GET (RFC 9110 asks every server to answer it): the headers of
    the GET, no body; a path without GET refuses it as it refuses GET."""
    for path in ("/healthz", "/v1/models", "/openapi.json"):
        got, head = oracle_client.get(path), oracle_client.head(path)
        assert head.status_code == got.status_code == 200 and head.content == b"", path
        assert head.headers["content-length"] == got.headers["content-length"] == str(len(got.content))
        assert head.headers["content-type"] == got.headers["content-type"]
    assert oracle_client.head("/v1/reconstructions/nojob").status_code == 404
    refused = oracle_client.head("/v1/predict")
    assert refused.status_code == 405 and refused.content == b"" and refused.headers["allow"] == "OPTIONS, POST"


def test_every_documented_method_is_in_allow(oracle_client: TestClient) -> None:
    spec = oracle_client.get("/openapi.json").json()
    for path, ops in spec["paths"].items():
        concrete = path.replace("{job_id}", "abc")
        allow = {m.strip().lower() for m in oracle_client.options(concrete).headers["allow"].split(",")}
        assert set(ops) <= allow, (path, allow)


def test_a_path_with_no_route_says_where_the_routes_are(oracle_client: TestClient) -> None:
    """A client whose server URL ends in /v1 asks /v1/v1/models: the 404 says why, not just "Not Found";
    a route's own 404 (an unknown job) keeps its detail."""
    r = oracle_client.get("/v1/v1/models")
    assert r.status_code == 404 and r.headers["content-type"].startswith("application/problem+json")
    assert "no route '/v1/v1/models'" in r.json()["detail"] and "ends in /v1" in r.json()["detail"]
    assert r.json()["type"] == "about:blank" and r.json()["title"] == "Not Found"     # RFC 9457: the status phrase
    r = oracle_client.delete("/v1/models")
    assert r.status_code == 405 and r.json()["title"] == "Method Not Allowed"
    assert oracle_client.get("/v1/reconstructions/abc").json()["detail"].startswith("job_id: no job")


def test_a_trailing_slash_is_not_redirected_and_the_problem_names_the_route(oracle_client: TestClient) -> None:
    """``POST /v1/predict/`` is a 404 naming ``/v1/predict``, not a 307 (which ``curl -L`` follows by
    sending the whole upload again)."""
    r = oracle_client.post("/v1/predict/", files={"stacks": ("a.nii.gz", b"x")}, follow_redirects=False)
    assert r.status_code == 404 and r.headers["content-type"].startswith("application/problem+json")
    assert "the route is '/v1/predict', without the trailing slash" in r.json()["detail"]
    r = oracle_client.get("/v1/reconstructions/abc/", follow_redirects=False)
    assert r.status_code == 404 and "'/v1/reconstructions/abc', without" in r.json()["detail"]
    assert "routes start with /v1/" in oracle_client.get("/v1/nothing/", follow_redirects=False).json()["detail"]


def test_the_operations_that_need_a_key_say_so_where_keys_are_set(oracle) -> None:  # noqa: ANN001
    """With ``SVRNET_API_KEYS``, every operation the keys protect declares the two ways to send one (so
    the page's "Authorize" sends it), and those open without a key declare none; a server without
    keys declares no scheme at all. A key sent as the page sends it is taken."""
    with make_client(ModelRegistry({"default": oracle}), api_keys="k1") as client:
        spec = client.get("/openapi.json").json()
        schemes = spec["components"]["securitySchemes"]
        assert schemes["apiKey"]["name"] == "X-API-Key" and schemes["bearer"]["scheme"] == "bearer"
        for path, ops in spec["paths"].items():
            for method, op in ops.items():
                declared = {next(iter(s)) for s in op.get("security", [])}
                want = {"bearer", "apiKey"} if path.startswith("/v1/") or path == "/metrics" else set()
                assert declared == want, (method, path)
        assert client.get("/v1/models", headers={"Authorization": "Bearer k1"}).status_code == 200
    with make_client(ModelRegistry({"default": oracle}), api_keys="k1", metrics_public=True) as client:
        assert "security" not in client.get("/openapi.json").json()["paths"]["/metrics"]["get"]
    with make_client(ModelRegistry({"default": oracle})) as client:
        spec = client.get("/openapi.json").json()
    assert "securitySchemes" not in spec.get("components", {})
    assert not [p for p, ops in spec["paths"].items() for op in ops.values() if "security" in op]


def test_fields_the_server_always_sends_are_required_in_its_schema(oracle) -> None:  # noqa: ANN001
    """A field every answer holds (null where it has no value) is required and nullable, so that a
    client generated from the schema reads it as always there: a slice's ``reason``, a job status's
    stage, error, result URLs and report."""
    with make_client(ModelRegistry({"default": oracle})) as client:
        schemas = client.get("/openapi.json").json()["components"]["schemas"]
    assert "reason" in schemas["SliceResult"]["required"]
    assert {"type": "null"} in schemas["SliceResult"]["properties"]["reason"]["anyOf"]
    status = schemas["JobStatus"]
    assert set(status["required"]) >= {"job_id", "status", "stage", "progress", "error", "result_url", "preview_url",
                                       "report", "expires_at"}
