"""The ``svrnet-train`` console entry point: the training command line, or one line naming what to install.

Training needs the ``train`` extra (torch, onnx, typer, rich, matplotlib); a server installation
without it gets that said instead of a traceback.
"""

from __future__ import annotations

from client.launch import run_or_name_missing

TRAIN_PACKAGES = ("torch", "onnx", "typer", "rich", "click", "matplotlib")
"""What the ``train`` extra installs beside the server's packages."""


def main() -> None:
    """Run ``svrnet-train``."""
    run_or_name_missing("model_export.cli", TRAIN_PACKAGES, "svrnet-train: the training packages are not installed "
                        "({name} is missing): pip install -c constraints.txt \".[train]\" (make test installs them)")
