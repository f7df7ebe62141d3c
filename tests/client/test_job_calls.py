"""Following a job: the wait goes on through a server's restart and a busy server, and ends where it must."""

from __future__ import annotations

import httpx
import pytest

from client import ConnectionFailed, ServerError, WaitTimeout
from tests.client.test_client import mock
from tests.support.client_fakes import FakeJobs, problem


def test_wait_goes_on_through_a_server_restart_and_gives_up_on_a_server_gone(no_sleep: list[float]) -> None:
    fake, down = FakeJobs(), {"left": 0, "status": None}

    def restarting(request: httpx.Request) -> httpx.Response:
        if request.method == "GET" and down["left"] > 0:
            down["left"] -= 1
            if down["status"] is None:
                raise httpx.ConnectError("[Errno 111] Connection refused", request=request)
            return httpx.Response(down["status"], json=problem(down["status"], "no replica"))
        return fake(request)

    svr = mock(restarting, retries=1)
    for status in (None, 502, 503):                  # refused connections (a restart), a proxy's 502, a 503 past retries
        job_id = svr.reconstruct([__file__])["job_id"]
        down.update(left=9, status=status)
        told: list[Exception | None] = []
        assert svr.wait(job_id, poll_s=0.0, on_unreachable=told.append)["status"] == "succeeded" and down["left"] == 0
        assert len(told) == 2 and told[0] is not None and told[1] is None     # once gone, once back
    job_id = svr.reconstruct([__file__])["job_id"]
    down.update(left=9, status=None)
    with pytest.raises(ConnectionFailed):
        svr.wait(job_id, poll_s=0.0, unreachable_s=0.0)
    down.update(left=1, status=500)                  # the server's own error is not waited out
    with pytest.raises(ServerError):
        svr.wait(job_id, poll_s=0.0)


def test_wait_waits_as_long_as_a_busy_server_asks(no_sleep: list[float]) -> None:
    fake, busy = FakeJobs(), {"left": 0}

    def saturated(request: httpx.Request) -> httpx.Response:
        if request.method == "GET" and busy["left"] > 0:
            busy["left"] -= 1
            return httpx.Response(503, json=problem(503, "busy"), headers={"Retry-After": "60"})
        return fake(request)

    svr = mock(saturated, retries=0)
    job_id = svr.reconstruct([__file__])["job_id"]
    busy["left"] = 2
    assert svr.wait(job_id, poll_s=1.0, unreachable_s=600.0)["status"] == "succeeded"
    assert sorted(no_sleep)[-2:] == [60.0, 60.0], no_sleep


def test_wait_times_out() -> None:
    svr = mock(FakeJobs("running"))
    job_id = svr.reconstruct([__file__])["job_id"]
    with pytest.raises(WaitTimeout) as e:
        svr.wait(job_id, poll_s=0.01, timeout_s=0.05)
    assert e.value.job["status"] == "running"


def test_waiting_on_a_server_that_never_answered_ends_at_once(no_sleep: list[float]) -> None:
    calls = []

    def stopped(request: httpx.Request) -> httpx.Response:
        calls.append(request.method)
        raise httpx.ConnectError("[Errno 111] Connection refused", request=request)

    with pytest.raises(ConnectionFailed, match="Connection refused"):
        mock(stopped, retries=2).wait("3f2a", poll_s=1.0, timeout_s=3600.0, unreachable_s=120.0)
    assert calls == ["GET"] * 3 and sum(no_sleep) < 5              # the transport's retries, not 120 s of polls


def test_following_a_job_says_when_the_server_stops_answering_and_when_it_answers_again(capsys) -> None:  # noqa: ANN001
    """A user watching a wait is told why nothing moves (the job goes on), not left in silence."""
    from types import SimpleNamespace

    from client.cli_support import follow_job

    def wait(job_id: str, poll_s: float, timeout_s: float, on_progress, on_unreachable) -> dict:  # noqa: ANN001
        on_unreachable(ConnectionFailed("GET /v1/reconstructions/j1: Connection refused"))
        on_unreachable(None)
        return {"status": "succeeded"}

    assert follow_job(SimpleNamespace(wait=wait), "j1", 1.0, 60.0) == {"status": "succeeded"}
    said = " ".join(capsys.readouterr().err.split())
    assert "job j1: the server does not answer (GET /v1/reconstructions/j1: Connection refused)" in said
    assert "the job goes on on the server" in said and "job j1: the server answers again" in said

    from client import Busy

    def busy(job_id: str, poll_s: float, timeout_s: float, on_progress, on_unreachable) -> dict:  # noqa: ANN001
        on_unreachable(Busy("GET /v1/reconstructions/j1: 429 Too Many Requests"))
        return {"status": "succeeded"}

    follow_job(SimpleNamespace(wait=busy), "j1", 1.0, 60.0)
    said = " ".join(capsys.readouterr().err.split())
    assert "job j1: the server is busy (" in said and "does not answer" not in said
