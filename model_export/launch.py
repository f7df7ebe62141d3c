"""The ``svrnet-train`` console entry point: the training command line, or one line naming what to install.

Training needs the ``train`` extra (torch, onnx, typer, rich, matplotlib); a server installation
without it gets that said instead of a traceback.
"""

from __future__ import annotations

import sys

TRAIN_PACKAGES = ("torch", "onnx", "typer", "rich", "click", "matplotlib")
"""What the ``train`` extra installs beside the server's packages."""


def main() -> None:
    """Run ``svrnet-train``; exit 1 with one line when a package of the ``train`` extra is missing."""
    try:
        from model_export.cli import app
    except ModuleNotFoundError as missing:
        if (missing.name or "").split(".")[0] not in TRAIN_PACKAGES:
            raise
        sys.exit(f"svrnet-train: the training packages are not installed ({missing.name} is missing): "
                 "pip install -c constraints.txt \".[train]\" (make test installs them)")
    app()
