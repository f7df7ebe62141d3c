"""Reconstruction jobs: ``/v1/reconstructions`` (submit, status, volume, preview, refined poses, cancel)."""

from __future__ import annotations

import asyncio
import logging
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated, Optional

from anyio import to_thread
from fastapi import APIRouter, Depends, Form, Header, Query, Request, Response
from fastapi.responses import FileResponse
from starlette.types import Receive, Scope, Send

from service.api.access import job_owner, presented_key
from service.api.deps import (IDEMPOTENCY_HEADER, ApiKey, LocalisersDep, RegistryDep, SettingsDep, full_queue,
                              idempotency_digest, localiser_for, localiser_for_regions, processing, queue_full,
                              requested_model)
from service.api.idempotency import hold_submission, made_by_key, submission_digest, unless_abandoned
from service.api.job_submission import SLICE_THICKNESS_HELP, ThicknessField, check_submission, thickness_per_stack
from service.api.problems import problem
from service.api.schemas import UPLOAD_ERRORS, JobCreated, JobStatus, RefinedPoses, download, problem_responses
from service.api.uploads import UploadForm, UploadFormDep, known_fields, upload_directory, upload_reader
from service.core.cancellation import checkpoint
from service.core.errors import Conflict, InvalidParameter, NotFound, PayloadTooLarge, QueueFull, Saturated
from service.core.settings import Settings
from service.jobs.job_inputs import keep_decoded, keep_json
from service.jobs.store import FINAL, Job, JobStore
from service.reconstruction.export import volume_in_stack_space, zip_folder
from service.reconstruction.stack_space import NoStackFrame

log = logging.getLogger(__name__)

router = APIRouter(prefix="/v1/reconstructions", tags=["reconstruction"], dependencies=[ApiKey])


def _store(request: Request) -> JobStore:
    return request.app.state.job_store


def _iso(t: float) -> str:
    return datetime.fromtimestamp(t, timezone.utc).isoformat()


def _status(job: Job, workers: int | None = None, retention_s: float | None = None) -> dict:
    """A job's status object; ``coherent`` repeats the report's verdict (``quality.coherent``), so that a
    client reading only the status learns that a succeeded job's volume is no coherent brain;
    ``expires_at``, when a finished job's records and files are deleted (``retention_s`` after its last
    change: the stores' ``expire``)."""
    done = job.status == "succeeded"
    ends = retention_s is not None and job.status in FINAL
    base = f"/v1/reconstructions/{job.id}"
    quality = (job.report or {}).get("quality") if done else None
    return {"job_id": job.id, "status": job.status, "stage": job.stage, "progress": job.progress, "error": job.error,
            "created_at": _iso(job.created_at), "updated_at": _iso(job.updated_at),
            "result_url": f"{base}/volume" if done else None, "preview_url": f"{base}/preview.png" if done else None,
            "poses_url": f"{base}/poses" if done else None,
            "transforms_url": f"{base}/transforms" if done else None, "report": job.report, "attempts": job.attempts,
            "started_at": _iso(job.started_at) if job.started_at else None,
            "workers": workers if job.status == "queued" else None,
            "coherent": quality.get("coherent") if isinstance(quality, dict) else None,
            "expires_at": _iso(job.updated_at + retention_s) if ends else None}


async def _job(request: Request, job_id: str) -> Job:
    """The job ``job_id`` (404 when there is none, or when another API key made it), read off the event
    loop: a store that stalls (a Redis that does not answer) holds this request, not every other of
    the replica's. A job belongs to the key that submitted it: another client learns not even that
    it exists."""
    job = await to_thread.run_sync(_store(request).get, job_id)
    if job is not None and "owner" in job.params and job.params["owner"] != job_owner(request.app.state.settings,
                                                                                       request.headers):
        job = None                      # another client's (a job made by an earlier release has no owner: anyone's)
    if job is None:
        shown = job_id if len(job_id) <= 64 else f"{job_id[:32]}... ({len(job_id)} characters)"
        raise NotFound(f"job_id: no job {shown!r}")
    return job


MAX_POSES_BYTES = 64 << 20
"""The largest ``poses`` upload: a job's refined poses of 32 stacks of 128 slices take about 20 MB."""
async def _submit(request: Request, response: Response, settings: Settings, form: UploadForm, key: str | None,
                  params: dict) -> dict:
    """The job made from a valid submission (or the one an earlier submission with its key made):
    its files read and checked (4xx at once, leaving no job behind), then queued."""
    store = _store(request)
    raw = (await request.form()).get("poses")
    if hasattr(raw, "read") and (raw.size or 0) > MAX_POSES_BYTES:
        raise PayloadTooLarge(f"poses: {raw.size} bytes; the poses of a request's stacks take at most "
                              f"{MAX_POSES_BYTES >> 20} MB")
    poses_text = (await raw.read()).decode("utf-8", "replace") if hasattr(raw, "read") else raw
    if key is not None and (earlier := await to_thread.run_sync(store.job_for_key, key)) is not None:
        earlier = await to_thread.run_sync(unless_abandoned, store, earlier)
        return made_by_key(earlier, response, settings.retry_after_s, await submission_digest(form, poses_text, params))
    if (full := await to_thread.run_sync(queue_full, request.app.state)) is not None:
        raise full                                   # before the files are hashed: a busy server answers at once
    if key is not None:
        params = {**params, "idempotency_key": key, "request_digest": await submission_digest(form, poses_text, params)}
    try:
        job, made = await to_thread.run_sync(store.create_once, params, settings.max_queued_jobs)
    except QueueFull:                                # others filled the queue since the check above
        raise full_queue(settings) from None
    if not made:                                     # a submission with the same key came in meanwhile
        return made_by_key(job, response, settings.retry_after_s, params["request_digest"])
    holding = asyncio.create_task(hold_submission(store, job.id))
    try:
        return await _keep_submission(request, response, settings, form, poses_text, store, job)
    finally:
        holding.cancel()


async def _keep_submission(request: Request, response: Response, settings: Settings, form: UploadForm,
                           poses_text: str | None, store: JobStore, job: Job) -> dict:
    """The new ``job``'s files read and checked (4xx at once, leaving no job behind), then queued."""
    inputs = store.directory(job.id) / "inputs"
    inputs.mkdir()
    try:
        uploads = await to_thread.run_sync(upload_reader(settings), form.stacks, form.masks, inputs)
        localiser_for_regions(request.app.state.localisers, uploads)          # refused now, not failed later
        # Whole-volume work (seconds for many large stacks): off the event loop, which serves every
        # other request and stream meanwhile.
        await to_thread.run_sync(check_submission, uploads, form.orders, poses_text, inputs,
                                 job.params["resolution_mm"])
        await to_thread.run_sync(keep_decoded, uploads, inputs)      # the voxels wait for a worker, not the files
        checkpoint()               # a client gone before the job is queued leaves none: it could not learn its id
    except Exception:
        await to_thread.run_sync(store.delete, job.id)     # rejected input (or a client gone) leaves no job behind
        raise
    now = await to_thread.run_sync(store.get, job.id)
    if now is None or now.status != "queued":            # given up meanwhile (its lease lapsed): told, not queued
        raise Saturated(f"{IDEMPOTENCY_HEADER}: the job store gave this submission up while its files were read "
                        f"(job {job.id} is {now.status if now else 'gone'}); send it again with a new key",
                        retry_after_s=settings.retry_after_s)
    names = {"stacks": [u.filename for u in uploads], "masks": [u.mask_filename for u in uploads if u.mask_filename]}
    try:
        keep_json(names, inputs / "names.json")
        keep_json(job.params, inputs / "params.json")      # last: a job that has it was submitted whole
        await to_thread.run_sync(request.app.state.job_runner.submit, job.id)
    except Exception:
        await to_thread.run_sync(store.delete, job.id)     # never queued (a full disk, a queue not answering): no job
        raise
    log.info("job submitted", extra={"request_id": request.scope["state"]["request_id"], "job_id": job.id,
                                     "n_stacks": len(uploads)})           # the request's id, linked to its job's lines
    response.headers["Location"] = f"/v1/reconstructions/{job.id}"
    return {"job_id": job.id, "status": "queued", "status_url": f"/v1/reconstructions/{job.id}"}


@router.post("", status_code=202, response_model=JobCreated, summary="Start a reconstruction job",
             responses={202: {"headers": {"Location": {"description": "the job's status URL",
                                                       "schema": {"type": "string"}}}}, **UPLOAD_ERRORS},
             dependencies=[Depends(known_fields("poses"))])
async def submit(
    request: Request,
    response: Response,
    registry: RegistryDep,
    localisers: LocalisersDep,
    settings: SettingsDep,
    form: UploadFormDep,
    resolution_mm: Annotated[float, Form(gt=0.2, le=5.0, allow_inf_nan=False)] = 0.8,
    svr_iterations: Annotated[int, Form(ge=0, le=10)] = 3,
    atlas_frame: Annotated[bool, Form(description="re-estimate the reconstruction's atlas frame with the model on "
                                                  "slices re-cut from it (corrects the common error of the poses)")] = True,
    slice_thickness_mm: Annotated[Optional[list[ThicknessField]], Form(description=SLICE_THICKNESS_HELP)] = None,
    idempotency_key: Annotated[Optional[str], Header(alias=IDEMPOTENCY_HEADER, description=(
        "8 to 200 printable ASCII characters: a submission sent again with the key of an earlier one gets "
        "that job instead of a new one (for retries after a lost answer)"),
        json_schema_extra={"minLength": 8, "maxLength": 200, "pattern": "^[!-~]+$"})] = None,
) -> dict:
    """Validates the files now (4xx at once), then queues the job; poll ``Location``.

    ``poses`` (optional, a form field or a file): the JSON body ``/v1/predict`` returned for the
    same files; without it the job predicts first.
    """
    model = requested_model(request, registry, form.model)
    localiser_for(localisers, form.masks)            # the job's worker localises; refused now, not failed later
    thickness = thickness_per_stack(slice_thickness_mm, len(form.stacks))
    if len(request.headers.getlist(IDEMPOTENCY_HEADER)) > 1:      # not one chosen of two
        raise InvalidParameter(f"{IDEMPOTENCY_HEADER}: given more than once; send one key per submission")
    key = idempotency_digest(idempotency_key, presented_key(request.headers.get("authorization"),
                                                            request.headers.get("x-api-key")))
    async with processing(request, answer_only=False):
        return await _submit(request, response, settings, form, key, {
            "resolution_mm": resolution_mm, "svr_iterations": svr_iterations, "mc_samples": form.mc_samples,
            "variance_threshold": form.variance_threshold, "max_expected_error_mm": form.max_expected_error_mm,
            "model": model, "model_sha256": registry.served_sha256(model),   # the file the server serves now
            "slice_order": form.slice_order, "atlas_frame": atlas_frame,
            "masks_hold_csf": form.masks_hold_csf, "slice_thickness_mm": thickness,
            "owner": job_owner(settings, request.headers)})


@router.get("/{job_id}", summary="Job status", response_model=JobStatus, responses=problem_responses(401, 404))
async def status(request: Request, job_id: str) -> dict:
    """The job's state; a queued job's ``workers`` says how many workers serve the queue (0: none is
    running, and the job waits until one is started; null where the back-end cannot tell)."""
    job = await _job(request, job_id)
    workers = await to_thread.run_sync(request.app.state.job_runner.live_workers) if job.status == "queued" else None
    return _status(job, workers, request.app.state.settings.retention_hours * 3600.0)


class Download(FileResponse):
    """A result file; to ``HEAD`` (answered as ``GET`` by the middleware, which drops the body) its
    headers alone, the file not read."""

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope.get("state", {}).get("sent_method") == "HEAD":
            scope = {**scope, "method": "HEAD"}
        try:
            await super().__call__(scope, receive, send)
        except RuntimeError:            # Starlette's stat found no file: deleted or expired since the handler looked
            if Path(self.path).exists():
                raise
            gone = NotFound("job_id: the job's results were deleted or expired while they were asked for")
            await problem(gone.status, gone.title, gone.detail, gone.type)(scope, receive, send)


async def _result(request: Request, job_id: str, name: str, media_type: str, download: str,
                  job: Job | None = None) -> FileResponse:
    job = job or await _job(request, job_id)
    if job.status != "succeeded":
        raise Conflict(f"job_id: job {job_id} is {job.status}; results exist once it has succeeded")
    path = _store(request).directory(job_id) / "outputs" / name
    if not path.exists():
        raise NotFound(f"job_id: the results of job {job_id} have expired")
    return Download(path, media_type=media_type, filename=download)


@router.get("/{job_id}/volume", responses=download("application/gzip", 401, 404, 409),
            summary="The reconstructed volume (.nii.gz, atlas space or a stack's scanner coordinates)",
            response_class=FileResponse)
async def volume(request: Request, job_id: str, settings: SettingsDep, stack: Annotated[Optional[int], Query(
        ge=0, le=10_000, description="place the volume in the scanner coordinates of this stack (its index in "
                                     "the upload): where the brain was, on average, while that stack was acquired, "
                                     "so that it overlays the stack in a viewer; the same voxels, another affine "
                                     "(the report's stack_frames)")] = None) -> Response:
    """The volume in atlas space, or with ``stack`` in that stack's scanner coordinates."""
    if stack is None:
        return await _result(request, job_id, "volume.nii.gz", "application/gzip", f"{job_id}.nii.gz")
    job = await _job(request, job_id)
    if job.status != "succeeded":
        return await _result(request, job_id, "volume.nii.gz", "application/gzip", f"{job_id}.nii.gz", job)  # its 409
    path = _store(request).directory(job_id) / "outputs" / "volume.nii.gz"
    with upload_directory(settings.tmp_dir) as tmp:        # the request's scratch, removed with it
        try:
            placed = await to_thread.run_sync(volume_in_stack_space, path, job.report or {}, stack,
                                              tmp / "volume.nii.gz")
        except NoStackFrame as exc:
            raise NotFound(f"stack: {exc}") from None
        except OSError:
            raise NotFound(f"job_id: the results of job {job_id} have expired") from None
        content = placed.read_bytes()
    return Response(content, media_type="application/gzip",
                    headers={"Content-Disposition": f'attachment; filename="{job_id}_stack{stack}.nii.gz"'})


@router.get("/{job_id}/preview.png", responses=download("image/png", 401, 404, 409), summary="Three orthogonal mid-planes", response_class=FileResponse)
async def preview(request: Request, job_id: str) -> FileResponse:
    return await _result(request, job_id, "preview.png", "image/png", f"{job_id}.png")


@router.get("/{job_id}/poses", responses={200: {"model": RefinedPoses}, **problem_responses(401, 404, 409)},
            summary="Refined slice poses, in the /v1/predict schema", response_class=FileResponse)
async def poses(request: Request, job_id: str) -> FileResponse:
    """The ``/v1/predict`` body the job started from with every slice's pose refined by the reconstruction
    (``atlas_from_voxel`` and the pose fields; ``accepted``/``reason`` stay the model's), plus per slice
    ``included``, ``exclusion_reason``, ``weight``, ``ncc``. It is a valid ``poses`` input to a new job."""
    return await _result(request, job_id, "poses.json", "application/json", f"{job_id}_poses.json")


@router.get("/{job_id}/transforms", responses=download("application/zip", 401, 404, 409),
            summary="Per-slice ITK transforms (.zip of transforms/*.tfm and slice_transforms.txt)",
            response_class=FileResponse)
async def transforms(request: Request, job_id: str) -> FileResponse:
    """The job's ``transforms/`` folder as a zip archive: one ITK ``.tfm`` per slice (atlas LPS -> the
    uploaded stack's LPS, the reconstruction as the fixed image) and ``slice_transforms.txt``
    (docs/reconstruction.md, "Output files"); made from the folder when a job written before the
    archive existed is asked for it."""
    job = await _job(request, job_id)
    outputs = _store(request).directory(job_id) / "outputs"
    if job.status == "succeeded" and not (outputs / "transforms.zip").exists() and (outputs / "transforms").is_dir():
        await to_thread.run_sync(zip_folder, outputs / "transforms", outputs / "transforms.zip")
    return await _result(request, job_id, "transforms.zip", "application/zip", f"{job_id}_transforms.zip", job)


@router.delete("/{job_id}", status_code=204, responses=problem_responses(401, 404), summary="Cancel a job and delete its files")
async def cancel(request: Request, job_id: str) -> Response:
    """A queued or running job is cancelled (its status stays readable as ``cancelled``); a finished
    one is deleted with its files (then ``404``)."""
    job = await _job(request, job_id)
    await to_thread.run_sync(_cancel_or_delete, request, job)
    return Response(status_code=204)


def _cancel_or_delete(request: Request, job: Job) -> None:
    """Cancel ``job`` where it is queued or running, else delete it with its files (a worker's thread:
    the store and the queue may take their time)."""
    if job.status in ("queued", "running") and _store(request).cancel(job.id):
        request.app.state.job_runner.cancel(job.id)
    else:                               # finished, perhaps since it was read: deleted with its results
        _store(request).delete(job.id)
