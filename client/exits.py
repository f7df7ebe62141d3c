"""Exit codes of ``svrnet`` and how a client error becomes one: one red line on stderr, never a traceback.

Each :class:`~client.errors.SVRnetError` kind has a documented exit code (:data:`EXIT_CODES`); the
commands run inside :func:`errors`, which prints the error and ends the process with its code.

Example:
    >>> from client.errors import Busy
    >>> exit_code_for(Busy("503: the server is busy", status=503)) == EXIT_BUSY
    True
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager

import typer
from rich.console import Console

from client.errors import (ArgumentError, BadRequest, Busy, Conflict, ConnectionFailed, JobFailed, KeyReused,
                           NotFound, OriginNotAllowed, PayloadTooLarge, ServerError, SVRnetError, Unauthorized,
                           UnsupportedFile, UnusableInput, WaitTimeout)

EXIT_OK, EXIT_UNEXPECTED, EXIT_USAGE = 0, 1, 2
EXIT_CONNECTION, EXIT_UNAUTHORIZED, EXIT_BAD_INPUT, EXIT_NOT_FOUND = 3, 4, 5, 6
EXIT_BUSY, EXIT_JOB_FAILED, EXIT_SERVER, EXIT_CONFLICT, EXIT_TIMEOUT = 7, 8, 9, 10, 11
EXIT_NOTHING_USABLE = 12
EXIT_INTERRUPTED = 130
"""The request succeeded and its outputs are written, but nothing in them is worth using: no slice
accepted (``predict``, ``stream``; none to write, ``export``), a volume whose stacks do not predict
each other (``reconstruct``)."""

EXIT_CODES: list[tuple[type[SVRnetError] | tuple[type[SVRnetError], ...], int]] = [
    (ConnectionFailed, EXIT_CONNECTION),
    (Unauthorized, EXIT_UNAUTHORIZED),
    ((BadRequest, PayloadTooLarge, UnsupportedFile, UnusableInput), EXIT_BAD_INPUT),
    (NotFound, EXIT_NOT_FOUND),
    (Busy, EXIT_BUSY),
    (JobFailed, EXIT_JOB_FAILED),
    (ServerError, EXIT_SERVER),
    (Conflict, EXIT_CONFLICT),
    (WaitTimeout, EXIT_TIMEOUT),
]

EXIT_HELP = (
    "Exit codes: 0 ok · 1 unexpected error · 2 usage · 3 connection failed (or not an SVRnet server) · 4 unauthorized · "
    "5 bad input (400/413/415/422; a stream whose every slice is refused, whose session could not take them all, "
    "or a stack of which got no final poses) · "
    "6 not found · 7 busy (429/503/507 after retries) · "
    "8 job failed/cancelled · 9 server error (5xx) · 10 conflict (409; a submission's key held by another "
    "request) · 11 timed out waiting · "
    "12 nothing usable in the answer (no slice accepted, none to export; a volume that is no coherent brain), its "
    "files written · "
    "130 interrupted (Ctrl-C or SIGTERM; a job already submitted goes on on the server)."
)


def exit_code_for(error: BaseException) -> int:
    """The documented exit code of a client error.

    Example:
        >>> exit_code_for(UnusableInput("stacks: flat.nii.gz is 2D", status=422))
        5
    """
    for kinds, code in EXIT_CODES:
        if isinstance(error, kinds):
            return code
    return EXIT_UNEXPECTED


def stdout() -> Console:
    """The console commands print their results on: lines wrapped at a terminal's width, kept whole
    where the output goes to a file or a pipe (a script greps one line for one message)."""
    return _unwrapped_off_terminal(Console(highlight=False))


def stderr() -> Console:
    """The console errors go to (wrapped as :func:`stdout`)."""
    return _unwrapped_off_terminal(Console(stderr=True, highlight=False))


def _unwrapped_off_terminal(console: Console) -> Console:
    console.soft_wrap = not console.is_terminal
    return console


def fail(message: str, code: int) -> None:
    """Print ``message`` as one red line on stderr and end the command with exit ``code``."""
    stderr().print(f"error: {message}", style="bold red", markup=False, soft_wrap=True)
    raise typer.Exit(code)


@contextmanager
def interrupt_says(message: str) -> Iterator[None]:
    """A Ctrl-C (or SIGTERM, :func:`client.launch.stop_as_interrupt`) inside ends the command (exit
    130) with ``message``: what the interrupted call leaves on the server, and how to reach it.

    Example:
        >>> with interrupt_says("interrupted; nothing was sent"):
        ...     raise KeyboardInterrupt
        Traceback (most recent call last):
        ...
        typer.exceptions.Exit: 130
    """
    try:
        yield
    except KeyboardInterrupt:
        fail(message, EXIT_INTERRUPTED)


def job_goes_on(job_id: str, succeeded: bool = False) -> AbstractContextManager[None]:
    """:func:`interrupt_says` while a job is followed: the job goes on on the server, and how to reach
    it; while a ``succeeded`` job's results download, that they wait there (cancelling it would
    delete them)."""
    if succeeded:
        return interrupt_says(f"interrupted; job {job_id} succeeded and its results wait on the server: svrnet fetch "
                              f"{job_id} downloads them again")
    return interrupt_says(f"interrupted; job {job_id} goes on on the server: svrnet status {job_id}, svrnet fetch "
                          f"{job_id} (waits for it and downloads it), or svrnet cancel {job_id}")


def submitting(key: str) -> AbstractContextManager[None]:
    """:func:`interrupt_says` while a job is submitted: the server may hold the job already, and the
    same command with ``--idempotency-key`` gets that job instead of making a second one."""
    return interrupt_says(f"interrupted while the job was submitted; the server may hold it: run the same command "
                          f"again with --idempotency-key {key} to get that job, not a second one")


@contextmanager
def errors() -> Iterator[None]:
    """Client errors -> one red line on stderr and the documented exit code; never a traceback."""
    try:
        yield
    except (typer.Exit, typer.Abort, typer.BadParameter):   # typer's own ending: its exit code stands
        raise
    except SVRnetError as e:
        hint = ""
        if isinstance(e, OriginNotAllowed):
            hint = (" (the request carried a browser's Origin header of another site: send it without one, or "
                    "add that origin to the server's SVRNET_ALLOWED_ORIGINS)")
        elif isinstance(e, Unauthorized):
            hint = (" (the key sent was refused: check SVRNET_API_KEY or --api-key)" if e.key_sent
                    else " (give the key with SVRNET_API_KEY or --api-key)")
        if isinstance(e, KeyReused):
            hint = " (the server holds another request under this submission's key: submit it again)"
        if isinstance(e, Busy):
            tried = f"sent {e.attempts} times" if e.attempts > 1 else "sent once"
            asks = f"; it asks to retry in {e.retry_after_s:g} s" if e.retry_after_s is not None else ""
            hint = f" ({tried}{asks})"
        fail(" ".join(str(e).split()) + hint, exit_code_for(e))
    except ArgumentError as e:                             # the client's own checks of its arguments, by field
        fail(" ".join(str(e).split()), EXIT_USAGE)
    except KeyboardInterrupt:
        fail("interrupted", EXIT_INTERRUPTED)
    except OSError as e:
        fail(f"{type(e).__name__}: {e}", EXIT_UNEXPECTED)
    except Exception as e:  # noqa: BLE001 - the CLI promises no tracebacks
        fail(f"unexpected {type(e).__name__}: {e}", EXIT_UNEXPECTED)
