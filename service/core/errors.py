"""The one exception tree of the service. Each error knows its HTTP status and problem type;
:mod:`service.api.problems` is the only place that turns them into RFC 7807 responses.

Messages name the offending field or file and never contain patient information. Two errors here
never reach an answer and stand outside the tree: :class:`Cancelled` (a job's run stops) and
:class:`UnusableModelFile` (a start stops).
"""

from __future__ import annotations


class ServiceError(Exception):
    """Base class: ``status`` and ``title`` of the problem+json answer; ``detail`` is the message."""

    status = 400
    title = "Bad request"
    type = "about:blank"
    headers: dict[str, str] | None = None

    def __init__(self, detail: str) -> None:
        super().__init__(detail)
        self.detail = detail


class MalformedRequest(ServiceError):
    status, title, type = 400, "Malformed request", "/problems/malformed-request"


class Unauthorized(ServiceError):
    status, title, type = 401, "Unauthorized", "/problems/unauthorized"
    headers = {"WWW-Authenticate": "Bearer"}


class ForeignOrigin(ServiceError):
    """403: a browser page of another origin than the server's own (or one of ``allowed_origins``)
    sent the request: a page the user merely visits must not use a service on their machine."""

    status, title, type = 403, "Origin not allowed", "/problems/origin-not-allowed"


class NotFound(ServiceError):
    status, title, type = 404, "Not found", "/problems/not-found"


class Conflict(ServiceError):
    status, title, type = 409, "Conflict", "/problems/conflict"


class PayloadTooLarge(ServiceError):
    status, title, type = 413, "Upload too large", "/problems/payload-too-large"


class RequestTimeout(ServiceError):
    """408: the request body did not arrive in time (no data for the idle limit, or not whole by the
    upload deadline); the connection is closed after the answer."""

    status, title, type = 408, "Request timeout", "/problems/request-timeout"
    headers = {"Connection": "close"}


class UnsupportedFile(ServiceError):
    """The file cannot be read at all (not an image, unknown format, truncated)."""

    status, title, type = 415, "Unreadable or unsupported file", "/problems/unsupported-file"


class UnusableImage(ServiceError):
    """The file was read but cannot be used (2D, 4D, empty, NaN, mask grid mismatch ...)."""

    status, title, type = 422, "Unusable image", "/problems/unusable-image"


class KeyReused(ServiceError):
    """422: an idempotency key sent again with another request (other files, poses or options): the
    earlier job is not this request's, and a new job under the key would make it two."""

    status, title, type = 422, "Idempotency key reused", "/problems/idempotency-key-reused"


class InvalidParameter(ServiceError):
    """A form field is missing, out of range or inconsistent with another (API v1: "400 malformed request";
    422 is kept for files that were read but cannot be used)."""

    status, title, type = 400, "Invalid parameter", "/problems/invalid-parameter"


class SessionFull(InvalidParameter):
    """A stream session holds all the slices or memory it may: a client stops sending, ends the stacks
    it began and sends the rest in another session (a later, smaller slice might still fit, but a
    session that full is done)."""

    title, type = "Session full", "/problems/session-full"


class Saturated(ServiceError):
    """503: every processing slot is taken (``Retry-After`` says when to try again)."""

    status, title, type = 503, "Service saturated", "/problems/saturated"

    def __init__(self, detail: str, retry_after_s: int = 2) -> None:
        super().__init__(detail)
        self.headers = {"Retry-After": str(retry_after_s)}


class QueueFull(Saturated):
    """429: the reconstruction queue holds its maximum of jobs."""

    status, title, type = 429, "Too many queued jobs", "/problems/queue-full"

    @classmethod
    def holding(cls, max_queued: int, retry_after_s: int = 2) -> "QueueFull":
        """The refusal of a queue that holds ``max_queued`` jobs already."""
        return cls(f"{max_queued} reconstruction jobs are queued already; retry later", retry_after_s)


class StoreUnavailable(Saturated):
    """503: the job store does not answer (Redis, with the distributed back-end) or cannot be used
    (the embedded database on a read-only or full disk); retry later."""

    status, title, type = 503, "Job store unavailable", "/problems/store-unavailable"


class InsufficientStorage(Saturated):
    """507: the server's disk (its temporary or data folder) filled while it wrote what a request sent;
    the files are not at fault: retry later (and the operator frees space)."""

    status, title, type = 507, "Insufficient storage", "/problems/insufficient-storage"

    def __init__(self, detail: str = "the server's disk is full; the files were not read, retry later",
                 retry_after_s: int = 30) -> None:
        super().__init__(detail, retry_after_s)


class ClientGone(ServiceError):
    """499 (nginx's convention): the client closed its connection while its request was processed; the
    work stops at its next step (:func:`service.core.cancellation.checkpoint`) and no one gets the answer."""

    status, title, type = 499, "Client closed request", "/problems/client-closed-request"

    def __init__(self, detail: str = "the client closed its connection before the answer was ready") -> None:
        super().__init__(detail)


class InternalError(ServiceError):
    """500: a fault of the server, not of the request (details go to the log by type only)."""

    status, title, type = 500, "Internal server error", "/problems/internal-error"

    def __init__(self, detail: str = "an unexpected error occurred; quote the request id") -> None:
        super().__init__(detail)


class NotReady(ServiceError):
    status, title, type = 503, "Not ready", "/problems/not-ready"
    headers = {"Retry-After": "5"}


class Cancelled(Exception):
    """A job was cancelled while it ran: the reconstruction's ``cancel`` hook said so, or the worker
    found the job cancelled in the store. Not a client error: it never reaches an HTTP answer."""


class UnusableModelFile(Exception):
    """A model file of the models or localisers folder does not load (a truncated copy, another
    format, a file without the service's metadata). Raised at start; never reaches an HTTP answer:
    ``svrnet-server`` and ``svrnet-mrd`` stop with one line naming the file and its folder's setting
    (a job worker, which loads the default localiser for a job without masks, fails that job)."""
