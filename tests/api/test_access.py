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
