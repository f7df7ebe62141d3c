"""SVRnet thin client: the HTTP API v1 from Python (``SVRnetClient``) and the shell (``svrnet``).

Depends on httpx (and typer + rich for the command line) only: no numpy, torch or imaging libraries.

Example:
    >>> from client import SVRnetClient, UnusableInput
    >>> with SVRnetClient("http://127.0.0.1:8000") as svr:                # doctest: +SKIP
    ...     poses = svr.predict(["ax.nii.gz", "cor.nii.gz"], mc_samples=100)
"""

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:                     # what type checkers and IDEs see; at run time, imported on first use
    from client._client import DEFAULT_SERVER, SVRnetClient
    from client.errors import (ArgumentError, BadRequest, Busy, Conflict, ConnectionFailed, JobFailed, KeyReused, NotFound,
                               OriginNotAllowed, PayloadTooLarge, ServerError, SVRnetError, Unauthorized,
                               UnsupportedFile, UnusableInput, WaitTimeout, error_from_response)

_ERRORS = ("ArgumentError", "BadRequest", "Busy", "Conflict", "ConnectionFailed", "JobFailed", "KeyReused", "NotFound",
           "OriginNotAllowed", "PayloadTooLarge", "ServerError", "SVRnetError", "Unauthorized", "UnsupportedFile", "UnusableInput", "WaitTimeout",
           "error_from_response")

_SUBMODULES = ("cli", "errors", "exits", "job_views", "launch", "multipart", "scanner_stack", "slice_transforms",
               "stream", "transport", "upload_files", "views")

__all__ = ["SVRnetClient", "DEFAULT_SERVER", *_ERRORS]


def __getattr__(name: str) -> Any:
    """The package's names, imported when first used: ``svrnet`` (``client.launch``) can then say
    which packages are missing instead of failing on the package's import."""
    if name in ("SVRnetClient", "DEFAULT_SERVER"):
        return getattr(importlib.import_module("client._client"), name)
    if name in _ERRORS:
        return getattr(importlib.import_module("client.errors"), name)
    if name in _SUBMODULES:
        return importlib.import_module(f"client.{name}")
    raise AttributeError(f"module 'client' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__, *_SUBMODULES})
