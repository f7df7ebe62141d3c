"""The thin SVRnet client: the HTTP API v1 (``../shared/design/api-v1.md``) over :mod:`httpx`.

Only httpx and the standard library are used, so scanner-side scripts stay small.

Example:
    >>> from client import SVRnetClient
    >>> with SVRnetClient("http://127.0.0.1:8000") as svr:          # doctest: +SKIP
    ...     result = svr.predict(["stack1.nii.gz", "stack2.nii.gz"], mc_samples=50)
    ...     accepted = [s for st in result["stacks"] for s in st["slices"] if s["accepted"]]
"""

from __future__ import annotations

import json
import secrets
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any
from urllib.parse import quote

from client import transport
from client.errors import Busy, ConnectionFailed, JobFailed, ServerError, WaitTimeout
from client.mask_archive import write_mask_archive
from client.multipart import MultipartBody, ProgressCallback, form_value, order_fields
from client.transport import DEFAULT_SERVER, DEFAULT_TIMEOUT, PathLike, Transport
from client.upload_files import file_parts

__all__ = ["SVRnetClient", "DEFAULT_SERVER", "DEFAULT_TIMEOUT", "ProgressCallback", "PathLike"]

TERMINAL = ("succeeded", "failed", "cancelled")
JOB_STATES = ("queued", "running", *TERMINAL)


def not_svrnet(call: str, expected: str) -> ConnectionFailed:
    """The error for an answer of the wrong shape: another server, or another API, at the client's URL."""
    return ConnectionFailed(f"{call}: the answer holds no {expected}; the server at this URL does not speak SVRnet "
                            "API v1 (check the server URL and the server's version)")
UNREACHABLE_S = 120.0
"""How long :meth:`SVRnetClient.wait` goes on polling a server it cannot reach (a restart loads its
models in seconds to tens of seconds; the job goes on meanwhile)."""

class SVRnetClient(Transport):
    """A synchronous client of the SVRnet HTTP API v1.

    Args:
        base_url: the server, e.g. ``http://scanner-gpu:8000`` (default: ``SVRNET_SERVER``, else
            ``http://127.0.0.1:8000``, as the command line); ignored when ``http`` is given
            (that client's own ``base_url`` is used).
        api_key: sent as ``Authorization: Bearer <key>``; defaults to ``$SVRNET_API_KEY``.
        timeout: httpx timeouts; reads and writes get 300 s, since a large request takes a while.
        retries: how many times a ``429``/``503`` answer or a transport error (``GET`` only) is
            retried before :class:`~client.errors.Busy` / :class:`~client.errors.ConnectionFailed`
            is raised. Uploads are retried only on an answer with ``Retry-After``; a
            ``Retry-After`` longer than 30 s raises :class:`~client.errors.Busy` at once.
        transport: an ``httpx.BaseTransport`` for the client this object creates (e.g.
            ``httpx.MockTransport`` in tests).
        http: an existing ``httpx.Client`` to use instead (e.g. FastAPI's ``TestClient``); it is not
            closed by :meth:`close`.
        backoff_s: the first sleep of the exponential backoff used when no ``Retry-After`` came.

    Example:
        >>> with SVRnetClient("http://127.0.0.1:8000", api_key="secret") as svr:   # doctest: +SKIP
        ...     print([m["name"] for m in svr.models()])
        ['default']
    """

    @staticmethod
    def _job_path(job_id: str, suffix: str = "") -> str:
        if not job_id:
            raise ValueError("job_id is empty")
        return f"/v1/reconstructions/{quote(str(job_id), safe='')}{suffix}"


    # -- the API -------------------------------------------------------------------------------

    def health(self) -> dict[str, Any]:
        """``GET /healthz``.

        Example:
            >>> SVRnetClient().health()                               # doctest: +SKIP
            {'status': 'ok'}
        """
        return self._json(self._send("GET", "/healthz"))

    def models(self) -> list[dict[str, Any]]:
        """``GET /v1/models``: name, version, backbone, sha256, input geometry, default threshold.

        Example:
            >>> [m["name"] for m in SVRnetClient().models()]           # doctest: +SKIP
            ['default']
        """
        models = self._json(self._send("GET", "/v1/models"))
        if not (isinstance(models, list) and all(isinstance(m, dict) and isinstance(m.get("name"), str) for m in models)):
            raise not_svrnet("GET /v1/models", "a list of models")
        return models

    def predict(self, stacks: Sequence[PathLike], masks: Sequence[PathLike] | None = None, *,
                mc_samples: int | None = None, variance_threshold: float | None = None,
                max_expected_error_mm: float | None = None,
                bias_correction: bool | None = None, model: str | None = None,
                slice_order: str | Sequence[str] | None = None, stack_consistency: bool | None = None,
                image_consistency: bool | None = None, masks_hold_csf: bool | None = None,
                progress: ProgressCallback | None = None) -> dict[str, Any]:
        """``POST /v1/predict``: the atlas pose and confidence of every slice of every stack.

        Only the optional parameters that are given are sent; the server's defaults apply otherwise.

        Args:
            stacks: 1..32 files (``.nii``, ``.nii.gz``, ``.nrrd``, ``.mha``, ``.dcm``, ``.zip``).
            masks: none, or one brain mask per stack, in the same order (the fetal brain, not a box around it).
            mc_samples: Monte Carlo dropout passes per slice (1..1000).
            variance_threshold: slices above this geodesic variance are not accepted.
            max_expected_error_mm: slices whose returned pose's expected error (mm) exceeds it are
                not accepted (``high_expected_error``); default: the model's calibrated value.
            bias_correction: N4 bias-field correction before normalisation.
            model: a name listed by :meth:`models`.
            slice_order: the stacks' acquisition order, if known: one value for every stack or one
                per stack; each ``auto``, ``interleaved``, ``sequential``, ``interleaved-even-first``,
                ``interleaved-odd-first``, or the slice indices in the order they were acquired
                (``"0,2,4,1,3"``). Without it the server's motion model chooses.
            stack_consistency: decide each stack's left-right branch from all its slices, fit its
                motion model and flag the slices inconsistent with it (default on; off, every slice
                is answered alone, its branch undecided).
            image_consistency: refine the poses where slices of different stacks cross (default on;
                needs ``stack_consistency``).
            masks_hold_csf: the masks are the skull's inside (brain and the CSF around it, as manual
                fetal masks are usually drawn): the pose network sees them less their outer 2 mm.
            progress: ``progress(bytes_sent, total)`` during the upload.

        Returns:
            The contract's JSON body: ``request_id``, ``model``, ``stacks[].slices[]`` ...

        Raises:
            UnsupportedFile: 415. UnusableInput: 422. PayloadTooLarge: 413. Busy: still 429/503
            after the retries. ConnectionFailed, Unauthorized, NotFound, ServerError.

        Example:
            >>> r = SVRnetClient().predict(["ax.nii.gz"], masks=["ax_mask.nii.gz"], mc_samples=50)  # doctest: +SKIP
            >>> r["stacks"][0]["slices"][0]["atlas_from_voxel"]                                     # doctest: +SKIP
            [[...], [...], [...], [0, 0, 0, 1]]
        """
        fields = [(k, form_value(v)) for k, v in (("mc_samples", mc_samples),
                                                   ("variance_threshold", variance_threshold),
                                                   ("max_expected_error_mm", max_expected_error_mm),
                                                   ("bias_correction", bias_correction), ("model", model),
                                                   ("stack_consistency", stack_consistency),
                                                   ("image_consistency", image_consistency),
                                                   ("masks_hold_csf", masks_hold_csf))
                  if v is not None]
        fields += order_fields(slice_order)
        body = MultipartBody(fields, file_parts(stacks, masks))
        return _with_stacks(self._json(self._send("POST", "/v1/predict", body=body, progress=progress)),
                            "POST /v1/predict")

    def masks(self, stacks: Sequence[PathLike], out_dir: PathLike, *, model: str | None = None,
              margin_mm: float | None = None, progress: ProgressCallback | None = None,
              overwrite: bool = False) -> dict[str, Any]:
        """``POST /v1/masks``: the server's brain mask of every stack, written into ``out_dir``.

        Each mask is ``<stem>_mask.nii.gz`` on its stack's own grid (uint8 0/1), grown outward by
        ``margin_mm`` when given (the localiser's masks are the skull's inside); ``report.json`` lies
        beside them. Only the archive's own plain file names are written, never a path it names.
        Masks of those names already in ``out_dir`` (a hand-drawn ``axial_mask.nii.gz`` beside its
        stack, say) are kept, and nothing is written, unless ``overwrite``; each file is written
        whole or not at all. A ``report.json`` there from an earlier call keeps its entries for the
        masks still beside it: the folder's report describes every mask in it.

        Returns:
            The report: ``stacks[]`` with ``filename``, ``mask``, ``brain_volume_ml``, ``confidence``,
            ``slices_with_brain``.

        Example:
            >>> SVRnetClient().masks(["ax.nii.gz"], "masks/")["stacks"][0]["confidence"]   # doctest: +SKIP
            0.97
        """
        fields = [(k, v) for k, v in (("model", model), ("margin_mm", margin_mm)) if v is not None]
        body = MultipartBody(fields, file_parts(stacks, None))
        response = self._send("POST", "/v1/masks", body=body, progress=progress)
        return write_mask_archive(response.content, Path(out_dir), overwrite, status=response.status_code,
                                  request_id=response.headers.get("x-request-id"))

    def reconstruct(self, stacks: Sequence[PathLike], masks: Sequence[PathLike] | None = None,
                    poses: Mapping[str, Any] | PathLike | None = None, *, resolution_mm: float | None = None,
                    svr_iterations: int | None = None, mc_samples: int | None = None,
                    variance_threshold: float | None = None, max_expected_error_mm: float | None = None,
                    slice_order: str | Sequence[str] | None = None, atlas_frame: bool | None = None,
                    masks_hold_csf: bool | None = None, slice_thickness_mm: float | Sequence[float] | None = None,
                    model: str | None = None, progress: ProgressCallback | None = None) -> dict[str, Any]:
        """``POST /v1/reconstructions``: start a slice-to-volume reconstruction job.

        Args:
            stacks: the stacks, as for :meth:`predict`.
            masks: none, or one mask per stack.
            poses: the body :meth:`predict` returned for the same files (a dict, or the path of a
                JSON file holding it); sent as the file field ``poses`` (``application/json``).
                Without it the job predicts first.
            resolution_mm: isotropic output spacing (server default 0.8).
            svr_iterations: slice-to-volume registration iterations (server default 3).
            mc_samples: as for :meth:`predict`.
            variance_threshold: as for :meth:`predict`.
            max_expected_error_mm: as for :meth:`predict`.
            slice_order: as for :meth:`predict`.
            atlas_frame: re-estimate the reconstruction's atlas frame with the model (server default true).
            masks_hold_csf: as for :meth:`predict`.
            slice_thickness_mm: the slices' thickness (mm), one value for every stack or one per stack
                (server default: a DICOM file's SliceThickness, else the slice spacing).
            model: the pose model that predicts and re-estimates the atlas frame, as for :meth:`predict`
                (default: the server's).
            progress: ``progress(bytes_sent, total)`` during the upload.

        Returns:
            ``{"job_id", "status", "status_url"}`` (``status_url`` filled from ``Location`` if absent).

        Example:
            >>> with SVRnetClient() as svr:                                      # doctest: +SKIP
            ...     job = svr.reconstruct(["a.nii.gz", "b.nii.gz"], resolution_mm=0.8)
            ...     svr.wait(job["job_id"])
            ...     svr.download_volume(job["job_id"], "recon.nii.gz")
        """
        fields = [(k, form_value(v)) for k, v in (("resolution_mm", resolution_mm),
                                                   ("svr_iterations", svr_iterations),
                                                   ("mc_samples", mc_samples),
                                                   ("variance_threshold", variance_threshold),
                                                   ("max_expected_error_mm", max_expected_error_mm),
                                                   ("atlas_frame", atlas_frame), ("masks_hold_csf", masks_hold_csf),
                                                   ("model", model))
                  if v is not None]
        fields += order_fields(slice_order)
        thickness = [slice_thickness_mm] if isinstance(slice_thickness_mm, (int, float)) else slice_thickness_mm or []
        fields += [("slice_thickness_mm", form_value(float(t))) for t in thickness]
        files: list[tuple[str, str, Path | bytes, str]] = list(file_parts(stacks, masks))
        if poses is not None:
            if isinstance(poses, Mapping):
                files.append(("poses", "poses.json", json.dumps(poses).encode(), "application/json"))
            else:
                path = Path(poses)
                if not path.is_file():
                    raise FileNotFoundError(f"poses: no such file: {path}")
                files.append(("poses", path.name, path, "application/json"))
        response = self._send("POST", "/v1/reconstructions", body=MultipartBody(fields, files), progress=progress,
                              headers={transport.IDEMPOTENCY_HEADER: secrets.token_urlsafe(24)})
        body = self._json(response)
        if isinstance(body, dict):
            location = response.headers.get("location")
            if location and not body.get("status_url"):
                body["status_url"] = location
            if "job_id" not in body and location:
                body["job_id"] = location.rstrip("/").rsplit("/", 1)[-1]
        if not (isinstance(body, dict) and isinstance(body.get("job_id"), str) and body["job_id"]):
            raise not_svrnet("POST /v1/reconstructions", "a job id")
        return body

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
             unreachable_s: float = UNREACHABLE_S) -> dict[str, Any]:
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
                unreachable_since = None
            except (ConnectionFailed, Busy, ServerError) as exc:
                if isinstance(exc, ServerError) and exc.status not in (502, 504):
                    raise                          # the server's own fault, not its absence
                if not self.answered and not isinstance(exc, Busy):
                    raise                          # never reached: no server to wait for at this address
                now = time.monotonic()
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
        """``GET /v1/reconstructions/{job_id}/volume``: the ``.nii.gz`` in atlas space, written to ``out_path``;
        with ``stack``, placed in that stack's scanner coordinates (its index in the upload; the same
        voxels, so that it overlays the stack in a viewer).

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
        return self._download(self._job_path(job_id, "/volume") + query, out_path, progress)

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
        return _with_stacks(self._json(self._send("GET", self._job_path(job_id, "/poses"))),
                            f"GET {self._job_path(job_id, '/poses')}")

    def cancel(self, job_id: str) -> None:
        """``DELETE /v1/reconstructions/{job_id}``: cancel a queued/running job and delete its files.

        Example:
            >>> SVRnetClient().cancel("3f2a")                                    # doctest: +SKIP
        """
        self._send("DELETE", self._job_path(job_id))


def _with_stacks(body: Any, call: str) -> dict[str, Any]:
    """``body`` where it is an answer of poses (an object with a ``stacks`` list), else the
    :func:`not_svrnet` error of ``call``: nothing is written from an answer of another server.

    Example:
        >>> _with_stacks({"stacks": []}, "POST /v1/predict")
        {'stacks': []}
        >>> _with_stacks([], "POST /v1/predict")
        Traceback (most recent call last):
        client.errors.ConnectionFailed: POST /v1/predict: ...
    """
    if not (isinstance(body, dict) and isinstance(body.get("stacks"), list)):
        raise not_svrnet(call, "an object with a stacks list")
    return body
