"""The ``svrnet`` console entry point: the command line, or one line naming what to install.

The command line needs the ``client`` extra (httpx, typer, rich; numpy, nibabel and websockets for
``svrnet stream``). An installation without it, e.g. ``pip install ".[server]"`` alone, gets that
said instead of a traceback.
"""

from __future__ import annotations

import sys

CLIENT_PACKAGES = ("httpx", "typer", "rich", "click", "websockets", "numpy", "nibabel")
"""What the ``client`` extra installs (and what they bring)."""


def main() -> None:
    """Run ``svrnet``; exit 1 with one line when a package of the ``client`` extra is missing."""
    try:
        from client.cli import app
    except ModuleNotFoundError as missing:
        if (missing.name or "").split(".")[0] not in CLIENT_PACKAGES:
            raise
        sys.exit(f"svrnet: the client's packages are not installed ({missing.name} is missing): "
                 "pip install \".[client]\" (make serve installs them)")
    app()
