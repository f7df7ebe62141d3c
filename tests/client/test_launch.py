"""``svrnet`` without the client's packages says what to install, in one line, instead of a traceback
(``run_without`` serves the training command line's test too)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def run_without(package: str, module: str) -> subprocess.CompletedProcess:
    code = f"import sys; sys.modules[{package!r}] = None; from {module} import main; main()"
    return subprocess.run([sys.executable, "-c", code, "--help"], cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_svrnet_without_httpx_names_the_extra_to_install() -> None:
    r = run_without("httpx", "client.launch")
    assert r.returncode == 1 and "httpx is missing" in r.stderr and '"svrnet[client]"' in r.stderr
    assert "Traceback" not in r.stderr


def test_with_the_packages_the_launchers_run_the_command_lines() -> None:
    r = subprocess.run([sys.executable, "-c", "from client.launch import main; main()", "--help"], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "predict" in r.stdout
