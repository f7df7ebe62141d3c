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
import numbers
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import httpx

from client import transport
from client.errors import Busy, ConnectionFailed, ServerError, SVRnetError
from client.mask_archive import write_mask_archive
from client.job_calls import JobCalls, not_svrnet, stacks_answer
from client.multipart import MultipartBody, ProgressCallback, form_value, order_fields
from client.transport import DEFAULT_SERVER, DEFAULT_TIMEOUT, PathLike
from client.upload_files import file_parts

__all__ = ["SVRnetClient", "DEFAULT_SERVER", "DEFAULT_TIMEOUT", "ProgressCallback", "PathLike"]

class SVRnetClient(JobCalls):
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
        verify: how an ``https://`` server's certificate is checked: a CA bundle's path or an
            ``ssl.SSLContext`` (default: the bundle ``SVRNET_CA_BUNDLE`` names, else the system's).

    Example:
        >>> with SVRnetClient("http://127.0.0.1:8000", api_key="secret") as svr:   # doctest: +SKIP
        ...     print([m["name"] for m in svr.models()])
        ['default']
    """

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
            ArgumentError: arguments refused before anything is sent (no stacks, masks not one per
            stack, an API key that cannot be sent); FileNotFoundError: a stack or mask that is not
            there. :meth:`masks` and :meth:`reconstruct` raise the same.

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
        return stacks_answer(self._json(self._send("POST", "/v1/predict", body=body, progress=progress)),
                            "POST /v1/predict")

    def masks(self, stacks: Sequence[PathLike], out_dir: PathLike, *, model: str | None = None,
              margin_mm: float | None = None, progress: ProgressCallback | None = None,
              overwrite: bool = False) -> list[dict[str, Any]]:
        """``POST /v1/masks``: the server's brain mask of every stack, written into ``out_dir``.

        Each mask is ``<stem>_mask.nii.gz`` on its stack's own grid (uint8 0/1), grown outward by
        ``margin_mm`` when given (the localiser's masks are the skull's inside); ``report.json`` lies
        beside them. Only the archive's own plain file names are written, never a path it names.
        Masks of those names already in ``out_dir`` (a hand-drawn ``axial_mask.nii.gz`` beside its
        stack, say) are kept, and nothing is written, unless ``overwrite``; each file is written
        whole or not at all. A ``report.json`` there from an earlier call keeps its entries for the
        masks still beside it: the folder's report describes every mask in it.

        Returns:
            The report, an object per stack: ``filename``, ``mask``, ``brain_volume_ml``, ``confidence``,
            ``slices_with_brain``, the ``localiser`` that made it.

        Raises:
            ArgumentError: masks of those names already in ``out_dir`` (without ``overwrite``), and as
            for :meth:`predict`.

        Example:
            >>> SVRnetClient().masks(["ax.nii.gz"], "masks/")[0]["confidence"]   # doctest: +SKIP
            0.97
        """
        fields = [(k, v) for k, v in (("model", model), ("margin_mm", margin_mm)) if v is not None]
        body = MultipartBody(fields, file_parts(stacks, None))
        response = self._send("POST", "/v1/masks", body=body, progress=progress)
        out = Path(out_dir).expanduser()                   # as a shell would (the CLI's come expanded)
        return write_mask_archive(response.content, out, overwrite, status=response.status_code,
                                  request_id=response.headers.get("x-request-id"))

    def reconstruct(self, stacks: Sequence[PathLike], masks: Sequence[PathLike] | None = None,
                    poses: Mapping[str, Any] | PathLike | None = None, *, resolution_mm: float | None = None,
                    svr_iterations: int | None = None, mc_samples: int | None = None,
                    variance_threshold: float | None = None, max_expected_error_mm: float | None = None,
                    slice_order: str | Sequence[str] | None = None, atlas_frame: bool | None = None,
                    masks_hold_csf: bool | None = None, slice_thickness_mm: float | Sequence[float] | None = None,
                    model: str | None = None, progress: ProgressCallback | None = None,
                    idempotency_key: str | None = None) -> dict[str, Any]:
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
            idempotency_key: the submission's key (default: a new random one), sent as
                ``Idempotency-Key``: a retry, or the same request sent again with the same key, gets the
                job the first made. An error after which the server may hold the job (a lost answer, a
                gateway's 5xx, a server that stayed busy after retries) names the key in its message
                and carries it as ``idempotency_key``: send the request again with it.

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
        thickness = [slice_thickness_mm] if isinstance(slice_thickness_mm, numbers.Real) else slice_thickness_mm or []
        fields += [("slice_thickness_mm", form_value(float(t))) for t in thickness]
        files: list[tuple[str, str, Path | bytes, str]] = list(file_parts(stacks, masks))
        if poses is not None:
            if isinstance(poses, Mapping):
                files.append(("poses", "poses.json", json.dumps(poses).encode(), "application/json"))
            else:
                path = Path(poses).expanduser()
                if not path.is_file():
                    raise FileNotFoundError(f"poses: no such file: {path}")
                files.append(("poses", path.name, path, "application/json"))
        key = idempotency_key or transport.new_idempotency_key()
        try:
            response = self._send("POST", "/v1/reconstructions", body=MultipartBody(fields, files), progress=progress,
                                  headers={transport.IDEMPOTENCY_HEADER: key})
        except SVRnetError as exc:
            exc.idempotency_key = key
            # The server may hold the job where the answer was lost (a dropped connection, a gateway's
            # 5xx) or where a busy server was asked more than once (the first may still be read).
            unsent = isinstance(exc.__cause__, (httpx.ConnectError, httpx.ConnectTimeout))     # never reached it
            maybe_made = (isinstance(exc, (ConnectionFailed, ServerError)) and not unsent) or (
                isinstance(exc, Busy) and (exc.attempts or 1) > 1)
            if maybe_made:
                sent = f"sent {exc.attempts} times" if (exc.attempts or 1) > 1 else "sent"
                exc.detail = (f"{exc.detail} (the request was {sent} with idempotency key {key}: the server may hold "
                              "its job; send it again with that key to get that job, not a second one)")
                exc.args = (exc.detail,)
            raise
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
