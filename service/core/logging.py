"""Structured (JSON lines) logs that never contain patient information.

Only whitelisted fields reach the log: request, job and stream session ids, route, method, status,
duration, counts and model names. File names, DICOM attributes and error details (which name files) are never logged.
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import sys
import time
import warnings

SAFE_FIELDS = ("request_id", "route", "method", "status", "duration_ms", "n_stacks", "n_slices", "model",
               "error_type", "error_at", "job_id", "stage", "session_id", "attempt")


def error_at(exc: BaseException) -> str:
    """Where in the service's own code ``exc`` was raised (``module:line function`` of the innermost
    frame under ``service/``): code, never data, so it may be logged.

    Example:
        >>> from service.reconstruction.grid import make_grid
        >>> try:
        ...     make_grid(-1.0, [[0.0, 0, 0], [1, 1, 1]])
        ... except ValueError as e:
        ...     where = error_at(e)
        >>> where.split(":")[0], where.split()[-1]
        ('service.reconstruction.grid', 'make_grid')
    """
    found = ""
    tb = exc.__traceback__
    while tb is not None:
        code = tb.tb_frame.f_code
        name = tb.tb_frame.f_globals.get("__name__", "")
        if name == "service" or name.startswith("service."):
            found = f"{name}:{tb.tb_lineno} {code.co_name}"
        tb = tb.tb_next
    return found


def timestamp(created: float) -> str:
    """A log line's time: ISO 8601 in UTC to the millisecond, with its zone (a request's lines, and the
    server's beside a worker's, fall within one second and must sort).

    Example:
        >>> timestamp(1796579547.1239)
        '2026-12-06T17:52:27.123Z'
    """
    seconds = int(created)
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(seconds)) + f".{int((created - seconds) * 1000):03d}Z"


class JsonFormatter(logging.Formatter):
    """One JSON object per line with the safe fields only; a record logged with its exception
    (``log.exception``, ``exc_info=True``) carries the exception's type and where in the service it
    was raised, never its message (which may name a file).

    Example:
        >>> try:
        ...     raise KeyError("jane_doe.nii.gz")
        ... except KeyError:
        ...     record = logging.LogRecord("service.x", logging.ERROR, "", 0, "upkeep failed", (), sys.exc_info())
        >>> line = JsonFormatter().format(record)
        >>> json.loads(line)["error_type"], "jane" in line
        ('KeyError', False)
    """

    def format(self, record: logging.LogRecord) -> str:
        out = {"ts": timestamp(record.created), "level": record.levelname, "logger": record.name,
               "msg": record.getMessage()}
        if record.exc_info and record.exc_info[1] is not None:
            out.update(error_type=type(record.exc_info[1]).__name__, error_at=error_at(record.exc_info[1]))
        out.update({k: getattr(record, k) for k in SAFE_FIELDS if hasattr(record, k)})
        return json.dumps(out)


QUIET = {"pydicom": logging.CRITICAL, "multipart": logging.ERROR, "python_multipart": logging.ERROR,
         "nibabel": logging.CRITICAL, "nibabel.global": logging.CRITICAL}
"""Libraries whose messages may quote what they parse (pydicom a DICOM attribute's value, the form
parser a body's bytes, nibabel a NIfTI header's fields, on a plain-text handler of its own): their
loggers only pass what stops them."""
QUIET_WARNINGS = ("pydicom", "xsdata", "ismrmrd")
"""Packages whose Python warnings may quote a client's value (pydicom an attribute's, xsdata an MRD
XML header field's, such as a malformed birth date): ignored, as they would reach stderr as text."""


def configure(level: str = "info", libraries: tuple[str, ...] = ()) -> None:
    """Send the ``service`` loggers to stderr as JSON lines; quiet the libraries that parse clients'
    bytes (:data:`QUIET`, and the warnings of :data:`QUIET_WARNINGS`, which name a field and may
    quote its value). The loggers of ``libraries`` (``rq`` in a worker) go the same way, each line
    cut to its first (:class:`FirstLine`)."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter())
    root = logging.getLogger("service")
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    root.propagate = False
    cut = logging.StreamHandler(sys.stderr)          # a handler's filter sees its child loggers' records too
    cut.setFormatter(JsonFormatter())
    cut.addFilter(FirstLine())
    for name in libraries:
        library = logging.getLogger(name)
        library.handlers[:] = [cut]
        library.setLevel(level.upper())
        library.propagate = False
    for name, floor in QUIET.items():
        logging.getLogger(name).setLevel(floor)
    for module in QUIET_WARNINGS:
        warnings.filterwarnings("ignore", module=rf"{module}(\.|$)")
    logging.captureWarnings(True)                  # the rest as JSON lines: their kind and place, not their text
    captured = logging.getLogger("py.warnings")
    captured.handlers[:] = [handler]
    captured.propagate = False
    captured.filters[:] = [WarningPlace()]


class FirstLine(logging.Filter):
    r"""A library's line cut to its first line: RQ appends a failed job's traceback, whose exception
    messages may name a client's file, to the line that says which job failed.

    Example:
        >>> record = logging.LogRecord("rq.worker", 40, "", 0, "job %s: raised (%s)\n%s", ("j1", "f", "Doe"), None)
        >>> FirstLine().filter(record), record.getMessage()
        (True, 'job j1: raised (f)')
    """

    def filter(self, record: logging.LogRecord) -> bool:
        record.msg, record.args = record.getMessage().split("\n", 1)[0], ()
        return True


class WarningPlace(logging.Filter):
    r"""A Python warning (``logging.captureWarnings``) logged by its category and the code that
    warned, never its text (which may quote a value: an overflow in a client's numbers, a field).

    Example:
        >>> record = logging.LogRecord("py.warnings", 30, "", 0, "/x/numpy/core/_methods.py:49: RuntimeWarning: "
        ...                            "overflow encountered in multiply (Doe)\n  return umr(a)\n", (), None)
        >>> WarningPlace().filter(record), record.getMessage(), record.error_type, record.error_at
        (True, 'a library warned', 'RuntimeWarning', '_methods.py:49')
    """

    def filter(self, record: logging.LogRecord) -> bool:
        found = re.match(r"(?:.*[\\/])?([^\\/]*?):(\d+): (\w+): ", str(record.msg))   # the file's name, line, category
        record.msg, record.args = "a library warned", ()
        record.error_type = found.group(3) if found else "Warning"
        record.error_at = f"{found.group(1)}:{found.group(2)}" if found else ""
        return True


def server_log_level(level: str) -> str:
    """The level for uvicorn's own loggers: never below ``info``. At ``debug`` uvicorn logs every
    WebSocket frame (stream slices, stack names, an ``auth`` message's API key) as text.

    Example:
        >>> server_log_level("debug"), server_log_level("warning")
        ('info', 'warning')
    """
    return "info" if level.lower() in ("debug", "trace") else level.lower()


class HandshakePaths(logging.Filter):
    """Rewrites uvicorn's line on each WebSocket handshake (``'%s - "WebSocket %s" ...'``, the path
    with its query string as the client sent it) to name a known route (``paths``) or
    ``(another path)``, the query string dropped: a client may put a patient's name or a key there.

    Example:
        >>> record = logging.LogRecord("uvicorn.error", 20, "", 0, '%s - "WebSocket %s" %d',
        ...                            ("1.2.3.4:5", "/v1/stream/Doe_Jane?key=k", 403), None)
        >>> HandshakePaths(["/v1/stream"]).filter(record), record.getMessage()
        (True, '- - "WebSocket (another path)" 403')
    """

    def __init__(self, paths: list[str] | tuple[str, ...] = ()) -> None:
        super().__init__()
        self.paths = frozenset(paths)

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str) and record.msg.startswith('%s - "WebSocket %s"') and len(record.args or ()) >= 2:
            path = str(record.args[1]).split("?", 1)[0]
            record.args = ("-", path if path in self.paths else "(another path)", *record.args[2:])
        return True


class GraceCancellations(logging.Filter):
    """Rewrites uvicorn's ``Exception in ASGI application`` ERROR for a request it cancelled because
    the server stopped past its shutdown grace (the request itself answered 503 and logged its line)
    as an INFO line saying so (none where the logger is set above INFO): a routine rolling restart
    raises no alert.

    Example:
        >>> import asyncio, sys
        >>> try:
        ...     raise asyncio.CancelledError()
        ... except asyncio.CancelledError:
        ...     record = logging.LogRecord("example.grace", 40, "", 0, "Exception in ASGI application\\n", (),
        ...                                sys.exc_info())
        >>> logging.getLogger("example.grace").setLevel(logging.INFO)
        >>> GraceCancellations().filter(record), record.levelname, record.getMessage(), record.exc_info
        (True, 'INFO', 'request cancelled: the server stopped past its shutdown grace', None)
    """

    def filter(self, record: logging.LogRecord) -> bool:
        cancelled = record.exc_info is not None and isinstance(record.exc_info[1], asyncio.CancelledError)
        if cancelled and isinstance(record.msg, str) and record.msg.startswith("Exception in ASGI application"):
            record.levelno, record.levelname = logging.INFO, "INFO"
            record.msg, record.args, record.exc_info, record.exc_text = \
                "request cancelled: the server stopped past its shutdown grace", (), None, None
            return logging.getLogger(record.name).isEnabledFor(logging.INFO)
        return True


def server_log_config(level: str, websocket_paths: tuple[str, ...] = ()) -> dict:
    """uvicorn's ``log_config``: its own loggers write the same JSON lines as the service's (a
    startup line, a refused request, an error in the server) at :func:`server_log_level`, an
    exception by its type and place only, so that stderr holds one format and no traceback; its
    WebSocket handshake lines name the route (one of ``websocket_paths``), never the path or query
    string sent, nor the client's address (:class:`HandshakePaths`); a request cancelled past the
    shutdown grace is an INFO line, not an ERROR (:class:`GraceCancellations`).

    Example:
        >>> config = server_log_config("debug")
        >>> config["formatters"]["json"]["()"].__name__, config["loggers"]["uvicorn.error"]["level"]
        ('JsonFormatter', 'INFO')
    """
    return {"version": 1, "disable_existing_loggers": False,
            "formatters": {"json": {"()": JsonFormatter}},
            "filters": {"handshakes": {"()": HandshakePaths, "paths": list(websocket_paths)},
                        "cancellations": {"()": GraceCancellations}},
            "handlers": {"stderr": {"class": "logging.StreamHandler", "formatter": "json", "stream": "ext://sys.stderr",
                                    "filters": ["handshakes", "cancellations"]}},
            "loggers": {name: {"handlers": ["stderr"], "level": server_log_level(level).upper(), "propagate": False}
                        for name in ("uvicorn", "uvicorn.error", "uvicorn.access")}}
