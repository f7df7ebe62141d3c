"""Following a reconstruction job over the HTTP API v1: its status, the wait for it, its files.

:class:`JobCalls` holds the calls on ``/v1/reconstructions/{job_id}`` that
:class:`~client.SVRnetClient` offers once a job is submitted; the answers of the wrong shape (another
server at the client's URL) raise :func:`not_svrnet`'s error, never write a file.

Example:
    >>> from client import SVRnetClient
    >>> with SVRnetClient("http://127.0.0.1:8000") as svr:          # doctest: +SKIP
    ...     svr.wait("3f2a", on_progress=lambda s: print(s["stage"], s["progress"]))
    ...     svr.download_volume("3f2a", "recon.nii.gz")
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import quote

from client import transport
from client.errors import Busy, ConnectionFailed, JobFailed, ServerError, WaitTimeout
from client.multipart import ProgressCallback
from client.transport import PathLike, Transport

TERMINAL = ("succeeded", "failed", "cancelled")
JOB_STATES = ("queued", "running", *TERMINAL)


def not_svrnet(call: str, expected: str) -> ConnectionFailed:
    """The error for an answer of the wrong shape: another server, or another API, at the client's URL."""
    return ConnectionFailed(f"{call}: the answer holds no {expected}; the server at this URL does not speak SVRnet "
                            "API v1 (check the server URL and the server's version)")


UNREACHABLE_S = 120.0
"""How long :meth:`JobCalls.wait` goes on polling a server it cannot reach (a restart loads its
models in seconds to tens of seconds; the job goes on meanwhile)."""


class JobCalls(Transport):
    """The calls on a reconstruction job of :class:`~client.SVRnetClient` (see there for the arguments)."""

    @staticmethod
    def _job_path(job_id: str, suffix: str = "") -> str:
        if not job_id:
            raise ValueError("job_id is empty")
        return f"/v1/reconstructions/{quote(str(job_id), safe='')}{suffix}"

    def status(self, job_id: str) -> dict[str, Any]:
        """``GET /v1/reconstructions/{job_id}``: status, stage, progress (0..1), error, report.

        Example:
            >>> SVRnetClient().status("3f2a")["status"]                    # doctest: +SKIP
            'running'
        """
        status = self._json(self._send("GET", self._job_path(job_id)))
        if not (isinstance(status, dict) and status.get("status") in JOB_STATES):
            raise not_svrnet(f"GET {self._job_path(job_id)}", "a job status")
        return status

    def wait(self, job_id: str, poll_s: float = 1.0, timeout_s: float = 3600.0,
             on_progress: Callable[[dict[str, Any]], None] | None = None,
             unreachable_s: float = UNREACHABLE_S,
             on_unreachable: Callable[[Exception | None], None] | None = None) -> dict[str, Any]:
        """Poll :meth:`status` until the job is ``succeeded``, ``failed`` or ``cancelled``.

        A server that restarts (its jobs go on: they are stored) or a load balancer without a
        replica for a while does not end the wait: once the server has answered this client (the
        job's submission, an earlier poll), polls that find no server go on for ``unreachable_s`` in
        a row before :class:`~client.errors.ConnectionFailed` is raised. A server that has answered
        nothing yet (a wrong address, a server not started) ends the wait at the first poll, after
        the transport's retries.

        Args:
            job_id: the job.
            poll_s: seconds between polls.
            timeout_s: give up (:class:`~client.errors.WaitTimeout`) after this long; the job goes on.
            on_progress: called with every status body (e.g. to draw ``body["progress"]``).
            unreachable_s: how long in a row the server may be unreachable or refuse to answer
                (refused connections, 502 / 504 from a proxy, 429 / 503 after the transport's retries).
            on_unreachable: called with the error when a poll first finds no server (the wait goes
                on), and with None when the server answers again (e.g. to tell a user why nothing moves).

        Returns:
            The final status body of a succeeded job.

        Raises:
            JobFailed: the job ended ``failed`` or ``cancelled``.
            WaitTimeout: ``timeout_s`` passed first.

        Example:
            >>> SVRnetClient().wait("3f2a", on_progress=lambda s: print(s["stage"], s["progress"]))  # doctest: +SKIP
        """
        deadline = time.monotonic() + timeout_s
        unreachable_since: float | None = None
        while True:
            try:
                job = self.status(job_id)
                if unreachable_since is not None and on_unreachable is not None:
                    on_unreachable(None)
                unreachable_since = None
            except (ConnectionFailed, Busy, ServerError) as exc:
                if isinstance(exc, ServerError) and exc.status not in (502, 504):
                    raise                          # the server's own fault, not its absence
                if not self.answered and not isinstance(exc, Busy):
                    raise                          # never reached: no server to wait for at this address
                now = time.monotonic()
                if unreachable_since is None and on_unreachable is not None:
                    on_unreachable(exc)
                unreachable_since = now if unreachable_since is None else unreachable_since
                if now - unreachable_since >= unreachable_s or now >= deadline:
                    raise
                asked = exc.retry_after_s if isinstance(exc, Busy) and exc.retry_after_s is not None else 0.0
                transport.sleep(min(max(poll_s * 2, asked), max(deadline - now, 0.0)))   # as long as the server asks
                continue
            if on_progress is not None:
                on_progress(job)
            state = job.get("status")
            if state == "succeeded":
                return job
            if state in ("failed", "cancelled"):
                raise JobFailed(job)
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise WaitTimeout(f"job {job_id} still {state} after {timeout_s:g} s; it goes on on the server "
                                  f"(svrnet fetch {job_id} waits for it again and downloads it)", job=job)
            transport.sleep(min(poll_s, remaining))

    def download_volume(self, job_id: str, out_path: PathLike,
                        progress: ProgressCallback | None = None, stack: int | None = None) -> Path:
        """``GET /v1/reconstructions/{job_id}/volume``: the ``.nii.gz`` in atlas space, written to ``out_path``
        (uncompressed where its name ends in ``.nii``, as viewers then read it); with ``stack``, placed
        in that stack's scanner coordinates (its index in the upload; the same voxels, so that it
        overlays the stack in a viewer).

        The file is written under a temporary name and renamed when complete.

        Raises:
            Conflict: 409, the job has not succeeded (yet). NotFound: unknown job, or a stack the job
            does not have or could not place.

        Example:
            >>> SVRnetClient().download_volume("3f2a", "recon.nii.gz")           # doctest: +SKIP
            PosixPath('recon.nii.gz')
            >>> SVRnetClient().download_volume("3f2a", "recon_stack0.nii.gz", stack=0)   # doctest: +SKIP
            PosixPath('recon_stack0.nii.gz')
        """
        query = "" if stack is None else f"?stack={int(stack)}"
        return self._download(self._job_path(job_id, "/volume") + query, out_path, progress,
                              gunzip=str(out_path).lower().endswith(".nii"))

    def download_preview(self, job_id: str, out_path: PathLike,
                         progress: ProgressCallback | None = None) -> Path:
        """``GET /v1/reconstructions/{job_id}/preview.png``: three orthogonal mid-planes, as PNG.

        Example:
            >>> SVRnetClient().download_preview("3f2a", "preview.png")           # doctest: +SKIP
            PosixPath('preview.png')
        """
        return self._download(self._job_path(job_id, "/preview.png"), out_path, progress)

    def download_transforms(self, job_id: str, out_path: PathLike,
                            progress: ProgressCallback | None = None) -> Path:
        """``GET /v1/reconstructions/{job_id}/transforms``: a zip of one ITK ``.tfm`` per slice (atlas
        space -> the uploaded stack's space, LPS) and ``slice_transforms.txt``.

        Example:
            >>> SVRnetClient().download_transforms("3f2a", "transforms.zip")     # doctest: +SKIP
            PosixPath('transforms.zip')
        """
        return self._download(self._job_path(job_id, "/transforms"), out_path, progress)

    def refined_poses(self, job_id: str) -> dict[str, Any]:
        """``GET /v1/reconstructions/{job_id}/poses``: the slice poses refined by the reconstruction.

        The body has the ``/v1/predict`` schema (``atlas_from_voxel`` and the pose fields refined;
        ``accepted`` stays the model's) plus, per slice, ``included``, ``exclusion_reason``, ``weight``
        and ``ncc``; it can be passed as ``poses`` to a new job.

        Raises:
            Conflict: 409, the job has not succeeded (yet). NotFound: unknown job.

        Example:
            >>> SVRnetClient().refined_poses("3f2a")["stacks"][0]["slices"][0]["included"]   # doctest: +SKIP
            True
        """
        return stacks_answer(self._json(self._send("GET", self._job_path(job_id, "/poses"))),
                            f"GET {self._job_path(job_id, '/poses')}")

    def cancel(self, job_id: str) -> None:
        """``DELETE /v1/reconstructions/{job_id}``: cancel a queued/running job and delete its files.

        Example:
            >>> SVRnetClient().cancel("3f2a")                                    # doctest: +SKIP
        """
        self._send("DELETE", self._job_path(job_id))


def stacks_answer(body: Any, call: str) -> dict[str, Any]:
    """``body`` where it is an answer of poses (an object with a ``stacks`` list), else the
    :func:`not_svrnet` error of ``call``: nothing is written from an answer of another server.

    Example:
        >>> stacks_answer({"stacks": []}, "POST /v1/predict")
        {'stacks': []}
        >>> stacks_answer([], "POST /v1/predict")
        Traceback (most recent call last):
        client.errors.ConnectionFailed: POST /v1/predict: ...
    """
    if not (isinstance(body, dict) and isinstance(body.get("stacks"), list)):
        raise not_svrnet(call, "an object with a stacks list")
    return body


__all__ = ["JOB_STATES", "JobCalls", "TERMINAL", "UNREACHABLE_S", "not_svrnet", "stacks_answer"]
