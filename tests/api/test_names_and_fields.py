"""Answers name the client's file (and the ZIP member), never a server temp file; names
are echoed without control characters; unknown form fields are refused by name."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.support import corpus
from tests.api.test_predict_errors import assert_problem, nifti_bytes, post, stack

BROKEN_DICOM = corpus.dicom(np.zeros((64, 64), np.uint16))[:-5000]      # pixel data cut short


def test_a_dicom_error_names_the_clients_file(oracle_client: TestClient) -> None:
    r = post(oracle_client, [("stacks", ("MR.1.2.840.dcm", BROKEN_DICOM))])
    assert_problem(r, 415, "MR.1.2.840.dcm")
    assert "stack0" not in r.text


def test_a_dicom_error_inside_a_zip_names_the_archive_and_the_member_by_its_place(oracle_client: TestClient) -> None:
    """Not by its name: scanners name the files of an export after the patient and the date
    (``DOE_JANE.MR.HASTE.0005.0008.2024.03.11...IMA``), and PACS exports their folders."""
    member = "series 3/DOE_JANE.MR.FETAL_HASTE.0005.0008.2024.03.11.10.15.07.IMA"
    r = post(oracle_client, [("stacks", ("study.zip", corpus.zipped({member: BROKEN_DICOM})))])
    assert_problem(r, 415, "study.zip: member 1 of 1: ")
    assert "00000.dcm" not in r.text and "svrnet-" not in r.text
    assert "series 3" not in r.text and "DOE" not in r.text and "2024" not in r.text


@pytest.mark.parametrize("name", ["scan\u202egpj.nii.gz", "scan\x1b[31m.nii.gz", "scan\u200b\x07.nii.gz"])
def test_control_characters_never_come_back(oracle_client: TestClient, oracle, name: str) -> None:  # noqa: ANN001
    r = post(oracle_client, [("stacks", (name, b"not an image" * 50))])
    assert r.status_code == 415
    detail = r.json()["detail"]
    assert not any(c in detail for c in "\u202e\x1b\x07\u200b"), detail
    assert "scan" in detail
    oracle.truth = np.broadcast_to(np.eye(4), (6, 4, 4)).copy()
    ok = post(oracle_client, [("stacks", (name, nifti_bytes(stack())))], {"mc_samples": "2"})
    assert ok.status_code == 200, ok.text
    filename = ok.json()["stacks"][0]["filename"]
    assert filename.startswith("scan") and filename.isprintable(), repr(filename)


def test_a_quote_in_a_file_name_comes_back_as_a_quote(oracle_client: TestClient, oracle) -> None:  # noqa: ANN001
    """httpx, like browsers, sends a ``"`` in a file name as ``%22``: the answer names the file as the
    client named it, in a refusal and in a stack's ``filename`` alike."""
    r = post(oracle_client, [("stacks", ('axial "1".nii.gz', b"not an image" * 50))])
    assert r.status_code == 415 and 'axial "1".nii.gz' in r.json()["detail"], r.json()["detail"]
    oracle.truth = np.broadcast_to(np.eye(4), (6, 4, 4)).copy()
    ok = post(oracle_client, [("stacks", ('axial "1".nii.gz', nifti_bytes(stack())))], {"mc_samples": "2"})
    assert ok.status_code == 200 and ok.json()["stacks"][0]["filename"] == 'axial "1".nii.gz', ok.text[:300]


@pytest.mark.parametrize(("route", "field"), [("/v1/predict", "bias_corection"), ("/v1/reconstructions", "bias_correction"),
                                               ("/v1/reconstructions", "svr_iteration")])
def test_unknown_form_fields_are_400_naming_them(oracle_client: TestClient, route: str, field: str) -> None:
    r = oracle_client.post(route, files=[("stacks", ("s.nii.gz", nifti_bytes(stack())))], data={field: "1"})
    assert_problem(r, 400, field, "unknown field")
    assert not oracle_client.app.state.job_store.queued()


def test_an_unknown_file_field_is_400_too(oracle_client: TestClient) -> None:
    r = oracle_client.post("/v1/predict", files=[("stacks", ("s.nii.gz", nifti_bytes(stack()))),
                                                 ("stack", ("t.nii.gz", b"x"))])
    assert_problem(r, 400, "stack:", "unknown field")


def test_the_fields_a_route_takes_come_from_its_signature() -> None:
    """A field added to a route is accepted at once: the allowed names are not a second list to keep."""
    from service.api.predict import predict
    from service.api.reconstructions import submit
    from service.api.uploads import declared_fields

    assert set(declared_fields(predict)) >= {"stacks", "masks", "mc_samples", "variance_threshold", "bias_correction",
                                         "model"}
    assert set(declared_fields(submit)) >= {"stacks", "masks", "resolution_mm", "svr_iterations", "mc_samples",
                                        "variance_threshold", "model"}


@pytest.mark.parametrize(("route", "fields"), [
    ("/v1/predict", [("model", "fast"), ("model", "default")]),
    ("/v1/predict", [("mc_samples", "2"), ("mc_samples", "")]),          # an empty copy would reset it to 100
    ("/v1/reconstructions", [("resolution_mm", "1.0"), ("resolution_mm", "2.0")]),
    ("/v1/masks", [("margin_mm", "5"), ("margin_mm", "10")]),
])
def test_a_field_of_one_value_given_twice_is_400_naming_it(oracle_client: TestClient, route: str,
                                                          fields: list[tuple[str, str]]) -> None:
    """Which copy would win is the form parser's accident; the client meant one of them."""
    r = oracle_client.post(route, files=[("stacks", ("s.nii.gz", nifti_bytes(stack()))), *fields])
    assert_problem(r, 400, fields[0][0], "given 2 times")
    assert not oracle_client.app.state.job_store.queued()


@pytest.mark.parametrize("field", ["model", "mc_samples", "masks_hold_csf"])
def test_a_field_sent_empty_is_400_not_its_default(oracle_client: TestClient, field: str) -> None:
    """FastAPI reads an empty form value as an absent one: ``model=`` would run the default model."""
    r = oracle_client.post("/v1/predict", files=[("stacks", ("s.nii.gz", nifti_bytes(stack())))], data={field: ""})
    assert_problem(r, 400, field, "empty")


@pytest.mark.parametrize("url", ["/v1/predict?mc_samples=5", "/v1/models?x=1", "/healthz?verbose=1",
                                 "/v1/reconstructions/abc/volume?stak=0"])
def test_an_unknown_query_parameter_is_400_naming_it(oracle_client: TestClient, url: str) -> None:
    """A misspelt ``?stak=0`` would serve the atlas-space volume; a form route's options go in its body."""
    method = oracle_client.post if url.startswith("/v1/predict") else oracle_client.get
    r = method(url, files=[("stacks", ("s.nii.gz", nifti_bytes(stack())))]) if method == oracle_client.post else method(url)
    assert_problem(r, 400, url.split("?")[1].split("=")[0], "unknown query parameter")


def test_a_query_parameter_given_twice_is_400(oracle_client: TestClient) -> None:
    r = oracle_client.get("/v1/reconstructions/abc/volume?stack=1&stack=0")
    assert_problem(r, 400, "stack", "given 2 times")


def test_list_fields_may_repeat(oracle_client: TestClient, oracle) -> None:  # noqa: ANN001
    oracle.truth = np.broadcast_to(np.eye(4), (12, 4, 4)).copy()            # two stacks of six slices
    r = oracle_client.post("/v1/predict", files=[("stacks", ("a.nii.gz", nifti_bytes(stack()))),
                                                 ("stacks", ("b.nii.gz", nifti_bytes(stack(seed=1))))],
                           data={"mc_samples": "2", "slice_order": ["sequential", "interleaved"]})
    assert r.status_code == 200, r.text
    assert [s["filename"] for s in r.json()["stacks"]] == ["a.nii.gz", "b.nii.gz"]
