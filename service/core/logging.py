"""Structured (JSON lines) logs that never contain patient information.

Only whitelisted fields reach the log: request id, route, method, status, duration, counts and
model names. File names, DICOM attributes and error details (which name files) are never logged.
"""

from __future__ import annotations

import json
import logging
import sys
import time

SAFE_FIELDS = ("request_id", "route", "method", "status", "duration_ms", "n_stacks", "n_slices", "model",
               "error_type", "error_at", "job_id", "stage")


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


class JsonFormatter(logging.Formatter):
    """One JSON object per line with the safe fields only."""

    def format(self, record: logging.LogRecord) -> str:
        out = {"ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)), "level": record.levelname,
               "logger": record.name, "msg": record.getMessage()}
        out.update({k: getattr(record, k) for k in SAFE_FIELDS if hasattr(record, k)})
        return json.dumps(out)


def configure(level: str = "info") -> None:
    """Send the ``service`` loggers to stderr as JSON lines."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter())
    root = logging.getLogger("service")
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    root.propagate = False
