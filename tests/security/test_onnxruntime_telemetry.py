"""onnxruntime keeps no device id nor usage events for the service's processes (its telemetry is off
once :mod:`service` or :mod:`model_export` is imported, before onnxruntime itself)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LOCALISER = ROOT / "service" / "localisers" / "default" / "model.onnx"


def _run_session(home: Path, first_import: str, telemetry: str | None = None) -> list[str]:
    """Files under ``home`` after a process imports ``first_import``, then onnxruntime, and opens a session."""
    env = {k: v for k, v in os.environ.items() if k != "ORT_DISABLE_TELEMETRY"} | {"HOME": str(home)}
    if telemetry is not None:
        env["ORT_DISABLE_TELEMETRY"] = telemetry
    code = (f"import {first_import}\nimport onnxruntime as ort\n"
            f"ort.InferenceSession({str(LOCALISER)!r}, providers=['CPUExecutionProvider'])\n")
    subprocess.run([sys.executable, "-c", code], env=env, cwd=ROOT, check=True, timeout=120)
    return sorted(str(p.relative_to(home)) for p in home.rglob("*") if p.is_file())


@pytest.mark.parametrize("package", ["service", "model_export"])
def test_the_packages_leave_no_telemetry_files(tmp_path: Path, package: str) -> None:
    assert _run_session(tmp_path, package) == []
    assert _run_session(tmp_path / "empty", package, telemetry="") == []    # an empty line of an env file


def test_onnxruntime_alone_would_keep_them(tmp_path: Path) -> None:
    """What the packages turn off: onnxruntime on its own writes its telemetry files (where a build
    has none, there is nothing to turn off and the test above holds trivially)."""
    files = _run_session(tmp_path, "sys")
    if not files:
        pytest.skip("this onnxruntime build keeps no telemetry files")
    assert any("onnxruntime" in f for f in files)


def test_a_setting_of_the_environment_is_kept(tmp_path: Path) -> None:
    """A site that sets the variable itself gets its own choice (here: telemetry on again)."""
    if not _run_session(tmp_path / "bare", "sys"):
        pytest.skip("this onnxruntime build keeps no telemetry files")
    assert _run_session(tmp_path / "set", "service", telemetry="0") != []
