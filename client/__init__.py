"""SVRnet thin client: the HTTP API v1 from Python (``SVRnetClient``) and the shell (``svrnet``).

Depends on httpx (and typer + rich for the command line) only: no numpy, torch or imaging libraries.

Example:
    >>> from client import SVRnetClient, UnusableInput
    >>> with SVRnetClient("http://127.0.0.1:8000") as svr:                # doctest: +SKIP
    ...     poses = svr.predict(["ax.nii.gz", "cor.nii.gz"], mc_samples=100)
"""

from client._client import DEFAULT_SERVER, SVRnetClient
from client.errors import (
    BadRequest,
    Busy,
    Conflict,
    ConnectionFailed,
    JobFailed,
    NotFound,
    PayloadTooLarge,
    ServerError,
    SVRnetError,
    Unauthorized,
    UnsupportedFile,
    UnusableInput,
    WaitTimeout,
    error_from_response,
)

__all__ = [
    "SVRnetClient", "DEFAULT_SERVER", "SVRnetError", "BadRequest", "Unauthorized", "NotFound", "Conflict",
    "PayloadTooLarge", "UnsupportedFile", "UnusableInput", "Busy", "ServerError", "ConnectionFailed", "JobFailed",
    "WaitTimeout", "error_from_response",
]
