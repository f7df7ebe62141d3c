"""The ``svrnet`` console entry point: the command line, or one line naming what to install.

The command line needs the ``client`` extra (httpx, typer, rich; numpy, nibabel and websockets for
``svrnet stream``). An installation without it, e.g. ``pip install ".[server]"`` alone, gets that
said instead of a traceback. :func:`run_or_name_missing` serves ``svrnet-train`` too
(``model_export/launch.py``), and :func:`installed_version` every command that names the release;
it imports nothing beyond the standard library.
"""

from __future__ import annotations

import importlib
import signal
import sys
from importlib.metadata import PackageNotFoundError, version

CLIENT_PACKAGES = ("httpx", "typer", "rich", "click", "websockets", "numpy", "nibabel")
"""What the ``client`` extra installs (and what they bring)."""


def installed_version() -> str | None:
    """The installed ``svrnet`` distribution's version (the client's and the server's, one package);
    None where the code runs from a folder that was not installed.

    Example:
        >>> installed_version() is None or installed_version()[0].isdigit()
        True
    """
    try:
        return version("svrnet")
    except PackageNotFoundError:
        return None


def run_or_name_missing(module: str, packages: tuple[str, ...], missing_says: str, entry: str = "app") -> None:
    """Call ``entry`` of ``module`` (a typer ``app``, or a console entry function); where importing
    the module misses one of ``packages``, exit 1 with ``missing_says`` (formatted with the missing
    package's ``name``) instead."""
    try:
        run = getattr(importlib.import_module(module), entry)
    except ModuleNotFoundError as missing:
        # a submodule's failed import may carry no ``name``: its message then names the module
        name = (missing.name or str(missing).partition("'")[2].partition("'")[0]).split(".")[0]
        if name not in packages:
            raise
        sys.exit(missing_says.format(name=name))
    run()


def stop_as_interrupt(signum: int, frame: object) -> None:
    """A SIGTERM (what systemd, a job scheduler's timeout or a CI runner sends) ends ``svrnet`` as a
    Ctrl-C does: the same message of what goes on on the server, exit 130, no half-written file."""
    raise KeyboardInterrupt


def main() -> None:
    """Run ``svrnet``."""
    signal.signal(signal.SIGTERM, stop_as_interrupt)
    run_or_name_missing("client.cli", CLIENT_PACKAGES, "svrnet: the client's packages are not installed ({name} is "
                        "missing): pip install \"svrnet[client]\" (in a checkout: make serve)")
