"""The ``svrnet`` console entry point: the command line, or one line naming what to install.

The command line needs the ``client`` extra (httpx, typer, rich; numpy, nibabel and websockets for
``svrnet stream``). An installation without it, e.g. ``pip install ".[server]"`` alone, gets that
said instead of a traceback. :func:`run_or_name_missing` serves ``svrnet-train`` too
(``model_export/launch.py``); it imports nothing beyond the standard library.
"""

from __future__ import annotations

import importlib
import sys

CLIENT_PACKAGES = ("httpx", "typer", "rich", "click", "websockets", "numpy", "nibabel")
"""What the ``client`` extra installs (and what they bring)."""


def run_or_name_missing(module: str, packages: tuple[str, ...], missing_says: str) -> None:
    """Run the typer ``app`` of ``module``; where importing it misses one of ``packages``, exit 1
    with ``missing_says`` (formatted with the missing package's ``name``) instead."""
    try:
        app = importlib.import_module(module).app
    except ModuleNotFoundError as missing:
        if (missing.name or "").split(".")[0] not in packages:
            raise
        sys.exit(missing_says.format(name=missing.name))
    app()


def main() -> None:
    """Run ``svrnet``."""
    run_or_name_missing("client.cli", CLIENT_PACKAGES, "svrnet: the client's packages are not installed ({name} is "
                        "missing): pip install \"svrnet[client]\" (in a checkout: make serve)")
