"""The service's logs: JSON lines of safe fields; libraries that parse clients' bytes kept quiet."""

from __future__ import annotations

import json
import logging
import warnings

import pytest

from service.core import logging as service_logging


@pytest.fixture(autouse=True)
def _restored_logging():  # noqa: ANN202 - configure() changes process-wide state: put it back
    loggers = [logging.getLogger(n) for n in ("service", *service_logging.QUIET)]
    saved = [(lg.handlers[:], lg.level, lg.propagate) for lg in loggers]
    with warnings.catch_warnings():
        yield
    for lg, (handlers, level, propagate) in zip(loggers, saved):
        lg.handlers[:], lg.level, lg.propagate = handlers, level, propagate


def test_libraries_that_quote_what_they_parse_pass_nothing_below_their_floor(capsys) -> None:  # noqa: ANN001
    service_logging.configure("debug")
    logging.getLogger("pydicom").warning("Value 'Doe^Jane' is not valid for VR DS")
    import nibabel.imageglobals                                      # its own plain-text handler on stderr
    nibabel.imageglobals.logger.error("magic string 'Doe ' is not valid")
    logging.getLogger("service.test").info("request", extra={"route": "/v1/predict", "stack_name": "Doe_Jane.nii",
                                                             "job_id": "3f2a", "attempt": 2})
    with warnings.catch_warnings(record=True) as caught:
        service_logging.configure("debug")                         # filters are set again inside catch_warnings
        warnings.warn_explicit("The PN component length (200) exceeds 64", UserWarning, "valuerep.py", 1,
                               module="pydicom.valuerep")
    assert not caught
    err = capsys.readouterr().err
    assert "Doe" not in err
    line = json.loads(err.strip().splitlines()[-1])
    assert line["route"] == "/v1/predict" and "stack_name" not in line
    assert (line["job_id"], line["attempt"]) == ("3f2a", 2)          # a job's attempt, as its id, is kept
    assert service_logging.server_log_level("DEBUG") == "info"     # uvicorn's frames never logged


def test_an_mrd_header_field_that_does_not_parse_is_not_quoted_on_stderr(capsys) -> None:  # noqa: ANN001
    ismrmrd = pytest.importorskip("ismrmrd")
    from service.mrd.send import mrd_header

    xml = mrd_header(4).toXML("utf-8")
    xml = (xml if isinstance(xml, str) else xml.decode()).replace(
        "<encoding>", "<subjectInformation><patientBirthdate>1990-02-30</patientBirthdate>"
        "<patientWeight_kg>72 kg</patientWeight_kg></subjectInformation><encoding>", 1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        service_logging.configure("debug")
        ismrmrd.xsd.CreateFromDocument(xml)                        # xsdata warns, quoting each value
    assert not [w for w in caught if "1990" in str(w.message) or "72 kg" in str(w.message)]
    assert "1990" not in capsys.readouterr().err


def test_uvicorns_own_lines_are_json_without_tracebacks() -> None:
    """The server's own lines (an error in a connection, with its exception) join the service's JSON
    lines on stderr: the exception's type and place, not its message or a traceback."""
    import subprocess
    import sys

    code = ("import logging, logging.config\n"
            "from service.core.logging import server_log_config\n"
            "logging.config.dictConfig(server_log_config('info'))\n"
            "try:\n    raise KeyError('jane_doe.nii.gz')\n"
            "except KeyError:\n    logging.getLogger('uvicorn.error').exception('Exception in ASGI application')\n")
    err = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60).stderr
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    line = json.loads(lines[0])
    assert line["logger"] == "uvicorn.error" and line["error_type"] == "KeyError" and "jane" not in err



def test_a_request_cancelled_past_the_shutdown_grace_is_an_info_line_not_an_error() -> None:
    """uvicorn cancels what still runs when the server stops past its grace and logs the cancellation
    as ``Exception in ASGI application``: one INFO line saying what happened (none at warning level),
    while any other exception stays an ERROR."""
    import subprocess
    import sys

    def lines(level: str) -> list[dict]:
        code = ("import asyncio, logging, logging.config\n"
                "from service.core.logging import server_log_config\n"
                f"logging.config.dictConfig(server_log_config({level!r}))\n"
                "for kind in (asyncio.CancelledError, KeyError):\n"
                "    try:\n        raise kind()\n"
                "    except BaseException:\n"
                "        logging.getLogger('uvicorn.error').exception('Exception in ASGI application\\n')\n")
        err = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60).stderr
        return [json.loads(line) for line in err.strip().splitlines()]

    cancelled, other = lines("info")
    assert cancelled["level"] == "INFO" and "shutdown grace" in cancelled["msg"] and "error_type" not in cancelled
    assert other["level"] == "ERROR" and other["error_type"] == "KeyError"
    assert [line["level"] for line in lines("warning")] == ["ERROR"]

def test_websocket_handshake_lines_name_the_route_never_the_path_or_query_sent() -> None:
    """uvicorn logs each WebSocket handshake with the path and query string as sent: a scanner script
    may put a patient's name or its key there. The line names the route, or 'another path'."""
    import subprocess
    import sys

    code = ("import logging, logging.config\n"
            "from service.core.logging import server_log_config\n"
            "logging.config.dictConfig(server_log_config('info', ('/v1/stream',)))\n"
            "log = logging.getLogger('uvicorn.error')\n"
            "log.info('%s - \"WebSocket %s\" [accepted]', '10.0.0.7:4242', '/v1/stream?patient=Doe_Jane&api_key=SECRET')\n"
            "log.info('%s - \"WebSocket %s\" 403', '10.0.0.7:4243', '/v1/stream/Doe_Jane_MRN4711')\n")
    err = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60).stderr
    messages = [json.loads(line)["msg"] for line in err.strip().splitlines()]
    assert messages == ['- - "WebSocket /v1/stream" [accepted]', '- - "WebSocket (another path)" 403'], err
    assert "Doe" not in err and "SECRET" not in err and "10.0.0.7" not in err


def test_a_line_s_time_is_utc_to_the_millisecond_with_its_zone() -> None:
    """Lines of one request, or of a server and a worker, fall within one second: they sort by ``ts``
    (ISO 8601, UTC, milliseconds truncated, never a 1000th)."""
    import datetime

    from service.core.logging import JsonFormatter

    record = logging.LogRecord("service.x", logging.INFO, "", 0, "request", (), None)
    record.created = 1796579547.9996
    ts = json.loads(JsonFormatter().format(record))["ts"]
    assert ts == "2026-12-06T17:52:27.999Z"
    assert datetime.datetime.fromisoformat(ts.replace("Z", "+00:00")).timestamp() == pytest.approx(record.created, abs=1e-3)
