"""The ``svrnet-train`` console entry point: the training command line, or one line naming what to install.

Training needs the ``train`` extra (torch, onnx, typer, rich, matplotlib); a server installation
without it gets that said instead of a traceback.
"""

from __future__ import annotations

from client.launch import run_or_name_missing
from service.launch import SERVER_PACKAGES

TRAIN_PACKAGES = ("torch", "onnx", "typer", "rich", "click", "matplotlib", *SERVER_PACKAGES)
"""What the ``train`` extra installs: its own packages and the server's."""


def main() -> None:
    """Run ``svrnet-train``."""
    run_or_name_missing("model_export.cli", TRAIN_PACKAGES, "svrnet-train: the training packages are not installed "
                        "({name} is missing): pip install \"svrnet[train]\" --extra-index-url https://download.pytorch.org/whl/cpu "
                        "(torch's CPU build; in a checkout: make install-dev)")
