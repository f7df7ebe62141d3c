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
               "error_type", "job_id", "stage")


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
