"""docs/cli.md is the reference of every ``svrnet`` command and option, generated from the CLI itself
(``typer client.cli utils docs``): a command or option added without it fails here."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
COMMAND = [sys.executable, "-m", "typer", "client.cli", "utils", "docs", "--name", "svrnet", "--title", "Command line: svrnet"]


def test_the_cli_reference_is_what_the_cli_says() -> None:
    made = subprocess.run(COMMAND, cwd=ROOT, capture_output=True, text=True, check=True, env={"COLUMNS": "80", "PATH": ""}).stdout
    assert made.strip() == (ROOT / "docs" / "cli.md").read_text().strip(), (
        "docs/cli.md is out of date: make cli-docs")
    assert "--max-expected-error" in made and "--api-key" in made and "svrnet reconstruct" in made
