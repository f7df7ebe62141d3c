"""Training, export, calibration and evaluation of the service's models (torch, offline).

It builds on :mod:`service`, whose import turns onnxruntime's telemetry off before anything here
imports onnxruntime.
"""

import service  # noqa: F401
