"""SVRnet thin client: the HTTP API v1 from Python (``SVRnetClient``) and the shell (``svrnet``).

Depends on httpx (and typer + rich for the command line) only: no numpy, torch or imaging libraries.

Example:
    >>> from client import SVRnetClient, UnusableInput
    >>> with SVRnetClient("http://127.0.0.1:8000") as svr:                # doctest: +SKIP
    ...     poses = svr.predict(["ax.nii.gz", "cor.nii.gz"], mc_samples=100)
"""

import importlib
from typing import Any

_ERRORS = ("BadRequest", "Busy", "Conflict", "ConnectionFailed", "JobFailed", "NotFound", "PayloadTooLarge",
           "ServerError", "SVRnetError", "Unauthorized", "UnsupportedFile", "UnusableInput", "WaitTimeout",
           "error_from_response")

__all__ = ["SVRnetClient", "DEFAULT_SERVER", *_ERRORS]


def __getattr__(name: str) -> Any:
    """The package's names, imported when first used: ``svrnet`` (``client.launch``) can then say
    which packages are missing instead of failing on the package's import."""
    if name in ("SVRnetClient", "DEFAULT_SERVER"):
        return getattr(importlib.import_module("client._client"), name)
    if name in _ERRORS:
        return getattr(importlib.import_module("client.errors"), name)
    raise AttributeError(f"module 'client' has no attribute {name!r}")
