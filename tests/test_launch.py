"""The server's console commands, installed with the client extra alone, say what to install."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
SERVER_ONLY = ("scipy", "fastapi", "fastapi_offline", "starlette", "uvicorn", "pydantic", "pydantic_settings",
               "multipart", "python_multipart", "onnxruntime", "SimpleITK", "prometheus_client", "PIL", "pydicom",
               "ismrmrd", "threadpoolctl", "isal")
"""What the server extra installs and the client extra does not: absent where the client's alone are."""


@pytest.mark.parametrize("command", ["svrnet-server", "svrnet-worker", "svrnet-mrd", "svrnet-mrd-send"])
def test_a_server_command_without_the_server_extra_names_it(command: str) -> None:
    module, _, function = SCRIPTS[command].partition(":")
    code = (f"import sys; sys.modules.update(dict.fromkeys({SERVER_ONLY!r})); sys.argv = [{command!r}, '--help']; "
            f"from {module} import {function}; {function}()")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    assert done.stderr.startswith(f"{command}: ") and '"svrnet[server]"' in done.stderr and " is missing" in done.stderr


def test_with_the_server_extra_a_command_runs() -> None:
    module, _, function = SCRIPTS["svrnet-server"].partition(":")
    code = f"import sys; sys.argv = ['svrnet-server', '--help']; from {module} import {function}; {function}()"
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "--port" in done.stdout, done.stderr


@pytest.mark.parametrize("entry", ["server", "worker", "mrd_server"])
def test_a_server_command_makes_its_files_private_before_any_import(entry: str) -> None:
    """The umask is 077 before the service is imported: an import that writes a file (onnxruntime's
    session file in the temporary folder) writes it readable by its user only."""
    code = ("import os, service.launch as launch; os.umask(0o022); "
            "launch.run_entry_point = lambda command, target: print(oct(os.umask(0o022))); "
            f"launch.{entry}()")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.stdout.strip() == "0o77", done.stderr


@pytest.mark.parametrize("entry", ["server", "worker", "mrd_server"])
def test_a_server_command_that_crashes_leaves_no_core_dump(entry: str, tmp_path: Path) -> None:
    """A crash (a decoder failing on a client's file) writes no core file of the process's memory,
    which holds the uploads it was reading, whatever core limit it was started with; the job
    workers it starts inherit the limit."""
    code = ("import ctypes, resource, service.launch as launch; "
            "hard = resource.getrlimit(resource.RLIMIT_CORE)[1]; "
            "resource.setrlimit(resource.RLIMIT_CORE, (hard, hard)); "
            "launch.run_entry_point = lambda command, target: (print(resource.getrlimit(resource.RLIMIT_CORE), "
            "flush=True), ctypes.string_at(0)); "
            f"launch.{entry}()")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == -signal.SIGSEGV, done.stderr
    assert done.stdout.strip() == "(0, 0)"
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith("core")]
