"""Job execution in worker processes (bounded concurrency), outside the request handlers.

A job folder holds ``inputs/`` (the uploaded stacks and masks as the submission decoded them,
:mod:`service.jobs.job_inputs`; ``params.json``, ``names.json``,
optional ``poses.json``: :mod:`service.jobs.uploaded_poses`) while the job is queued or running --
they are deleted as soon as it ends, whatever the outcome -- and, once done, ``outputs/``
(``volume.nii.gz``, ``preview.png``, ``report.json``, ``transforms/`` and ``transforms.zip``,
``poses.json``: the refined poses in the ``/v1/predict`` schema).

Stages (the job's ``stage``, with ``progress`` in 0..1): ``reading``, ``predicting poses`` (without
uploaded poses), then those of the reconstruction -- ``stack consistency``, ``stack registration``,
``slice starting poses``, ``gaussian average``, then per round ``registration k/K``,
``robust weighting k/K``, ``super-resolution k/K``; ``checking starting poses``, ``checking slice
level``, ``further slice-level pass`` and ``volume at the output resolution``
(:mod:`~service.reconstruction.never_worse`) -- ``atlas frame``, ``midline`` and ``writing``.
:func:`run_job` is what a worker process executes; it claims the job atomically, reports stage and
progress to the store, checks for cancellation between stages, and records any failure with its
reason. The back-ends run it: :mod:`service.jobs.local_runner` (the
embedded process pool) and :mod:`service.jobs.rq_runner` (workers on a Redis queue).
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from service.consistency.slice_order import SliceOrder, per_stack
from service.core.errors import Cancelled, InternalError, ServiceError, UnusableImage
from service.core.logging import error_at
from service.jobs.job_inputs import decoded_files, load_volume
from service.jobs.provenance import localiser_provenance, provenance
from service.jobs.starting_poses import lost_reasons, own_start, starting_poses, uploaded_start
from service.jobs.store import JobStore
from service.jobs.uploaded_poses import expected_errors, frame_added_mm, poses_from_predict_body

if TYPE_CHECKING:
    from service.inference.estimator import OnnxPoseEstimator, PoseEstimator
    from service.preprocess.localise import Localiser

log = logging.getLogger(__name__)


TIMED_OUT = "the job ran longer than SVRNET_JOB_TIMEOUT_H and was stopped"
MISSING_UPLOADS = ("the job's uploads are not in the worker's data folder: every API replica and worker must "
                   "share one SVRNET_DATA_DIR (docs/deployment.md); send the job again once they do")
"""A job's failure where its worker does not see the folder the API wrote its uploads to."""


NO_BRAIN_FOUND = ("masks: the localiser found no brain in any stack sent without a brain mask (every slice is "
                  "empty); upload a brain mask with each stack")
"""Why a job whose stacks came without masks has nothing to reconstruct (as /v1/predict's hint says it)."""


class Superseded(Exception):
    """A later run of the job (re-delivered by the queue) has claimed it: this run leaves everything to it."""


def _stack_files(inputs: Path) -> list[tuple[Path, Path | None]]:
    stacks = sorted(inputs.glob("stack*"), key=lambda p: int(p.name[5:]))
    return [(s, (inputs / f"mask{s.name[5:]}") if (inputs / f"mask{s.name[5:]}").exists() else None) for s in stacks]


def predicted_poses(uploads: list, estimator: PoseEstimator, mc_samples: int = 100,
                    variance_threshold: float | None = None) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[np.ndarray]]:
    """The reconstruction's start from the service's own prediction: ``[(atlas_from_voxel, include)]``
    and the brain masks (on each stack's grid) per stack; the poses are those ``/v1/predict`` answers
    for these uploads, ``include`` is :func:`starting_inclusion` (:func:`starting_poses`).
    """
    body, masks = predicted_body(uploads, estimator, mc_samples, variance_threshold)
    return starting_poses(body), masks


def uploaded_pose_masks(uploads: list, localiser: Localiser | None = None) -> list[np.ndarray]:
    """Each upload's brain as the pose network cut its slices (its mask, or ``localiser``'s, default
    the shipped one; the CSF rim of a mask that holds it inset): what a job that predicts its own
    poses reconstructs from (:func:`predicted_body`), so that a job given those poses reconstructs
    the same pixels."""
    from service.pipeline.prepare import localise_uploads

    return [found.pose_mask(u.volume.spacing, u.slice_axis)
            for found, u in zip(localise_uploads(uploads, localiser), uploads)]


def job_localiser(localisers_dir: Path | None, uploads: list) -> Localiser | None:
    """The server's default localiser (``SVRNET_LOCALISERS_DIR``, as ``/v1/predict`` runs it) where a
    stack came without a mask (or with a region around the head); None where every stack has its
    brain's, or no folder is given (the shipped one)."""
    if localisers_dir is None or not any(u.localised for u in uploads):
        return None
    from service.preprocess.localise import Localisers

    return Localisers.from_directory(localisers_dir, threads=1, names=("default",)).get()


MODEL_CHANGED = ("model: {name}'s file changed on disk since the job was submitted (sha256 {was} then, {now} now): "
                 "restart the server after adding or replacing a model, and submit the job again")
MODEL_GONE = "model: {name}'s file is no longer in the models folder or does not load: submit the job again"


def job_estimator(model_file: Path, required: bool = True,
                  sha256: str | None = None) -> tuple[OnnxPoseEstimator | None, float]:
    """The pose model a job names (one thread), and its atlas mid-sagittal plane: the plane its poses
    and the frame steps are in, given poses included (they come from that model's ``/v1/predict``).
    Not ``required`` (a job given poses) and the server without such a file: ``(None, the default
    plane)``; gone or unloadable where required, or another file than ``sha256`` (the one the server
    served when the job was submitted): a ``ValueError`` naming ``model``, which the job's error
    says (:data:`MODEL_GONE`, :data:`MODEL_CHANGED`)."""
    from service.geometry.twin import DEFAULT_PLANE_X_MM
    from service.inference.estimator import OnnxPoseEstimator
    from service.inference.model_file import load_model

    model_file = Path(model_file)
    if not required and not model_file.exists():
        return None, DEFAULT_PLANE_X_MM
    try:
        estimator = OnnxPoseEstimator(load_model(model_file, threads=1))
    except Exception:  # noqa: BLE001 - onnxruntime's own errors, a missing file: one account naming the field
        raise ValueError(MODEL_GONE.format(name=model_file.parent.name)) from None
    if sha256 is not None and estimator.info.sha256 != sha256:
        raise ValueError(MODEL_CHANGED.format(name=model_file.parent.name, was=sha256[:10],
                                              now=estimator.info.sha256[:10]))
    return estimator, estimator.info.symmetry_plane_x_mm


def predicted_body(uploads: list, estimator: PoseEstimator, mc_samples: int = 100,
                   variance_threshold: float | None = None, orders: list | None = None,
                   max_expected_error_mm: float | None = None,
                   localiser: Localiser | None = None, model_name: str | None = None) -> tuple[dict, list[np.ndarray]]:
    """The ``/v1/predict``-shaped body (``model``, ``mc_samples``, ``variance_threshold``, ``stacks``) of
    the service's own prediction, and the brain masks per stack; ``orders``: the stacks'
    acquisition orders (:class:`~service.consistency.slice_order.SliceOrder`), if known;
    ``localiser``: for the stacks without a mask (default: the shipped one); ``model_name``: the
    name the model is served under, as ``/v1/predict`` names it (default: its metadata's)."""
    from service.pipeline.documents import stack_objects
    from service.pipeline.predict import predict
    from service.pipeline.prepare import prepare_stacks

    info = estimator.info
    threshold = variance_threshold or info.variance_threshold
    prepared = prepare_stacks(uploads, info, bias_correction=True, workers=1, localiser=localiser)
    looked = any(p.localisation.method == "network" for p in prepared)
    if looked and not any(p.localisation.mask.any() for p in prepared):
        raise UnusableImage(NO_BRAIN_FOUND)
    max_expected = max_expected_error_mm or info.max_expected_error_mm
    predictions, _ = predict(prepared, estimator, mc_samples, threshold, orders=orders, max_expected_error_mm=max_expected)
    masks = [p.slices.to_stack(p.slices.masks) for p in prepared]
    return {"model": info.reference(model_name), "mc_samples": mc_samples, "variance_threshold": threshold,
            "max_expected_error_mm": max_expected, "localiser": localiser_provenance(uploads, localiser),
            "stacks": stack_objects(predictions)}, masks


def run_job(store: JobStore, models_dir: Path, job_id: str, redelivered: bool = False,
            localisers_dir: Path | None = None) -> None:
    """Execute one job (in a worker process of either back-end): claim it atomically, report stage and
    progress, stop at the next stage when it is cancelled, record any failure with its reason.

    ``redelivered``: the queue hands the job out again after the worker running it was lost;
    ``localisers_dir``: the server's localisers (default: the shipped one).
    """
    attempt = store.claim(job_id, redelivered=redelivered)
    if not attempt:
        return
    folder = store.directory(job_id)

    def progress(stage: str, fraction: float) -> None:
        job = store.get(job_id)
        if job is None or job.status == "cancelled":
            raise Cancelled
        if job.attempts != attempt:
            raise Superseded
        store.update(job_id, stage=stage, progress=float(min(max(fraction, 0.0), 1.0)))

    try:
        _execute(store, folder, Path(models_dir), job_id, progress, attempt, localisers_dir)
        log.info(f"job {job_id} completed, attempt {attempt}", extra={"job_id": job_id, "attempt": attempt})
    except Superseded:
        log.warning(f"job {job_id}: attempt {attempt} superseded by a re-delivery", extra={"job_id": job_id})
        return                         # the later run owns the job's files
    except Cancelled:
        log.info("job cancelled", extra={"job_id": job_id})
        shutil.rmtree(folder, ignore_errors=True)          # what the run wrote after the cancel deleted its files
    except Exception as exc:  # noqa: BLE001 - every failure is recorded on the job, not lost
        now = store.get(job_id)
        if now is not None and now.status != "cancelled" and now.attempts != attempt:
            log.warning(f"job {job_id}: attempt {attempt} failed after a re-delivery took it over", extra={"job_id": job_id})
            return                     # the later run owns the job's files, its inputs included
        # A failed job's results are no results: none stay; gone before the failure is recorded, which
        # on a disk the results filled is what lets the record be written (a job that ended is left).
        if now is not None and now.status in ("queued", "running"):
            shutil.rmtree(folder / "outputs", ignore_errors=True)
        if store.fail(job_id, failure_reason(exc), attempt):
            log.warning("job failed", extra={"job_id": job_id, "error_type": type(exc).__name__, "error_at": error_at(exc)})
        else:                          # cancelled meanwhile (its files deleted under the run): no failure
            log.info("job ended after it was cancelled or superseded", extra={"job_id": job_id})
            if store.is_cancelled(job_id):
                shutil.rmtree(folder, ignore_errors=True)
    # Ended, whatever the outcome: the uploads (raw headers, the clients' file names) go now, not at
    # the retention limit. A worker stopped mid-job never gets here, so a re-run still has them.
    store.discard_inputs(job_id)


def failure_reason(exc: Exception) -> str:
    """What the job's ``error`` says: the message of a service error (it names the file or field) or of
    a ``ValueError`` (the reconstruction's own account of unusable input, e.g. no slice left), else
    only the kind of failure -- other messages (OS, ITK) may hold server paths. The queue's time
    limit (RQ's ``JobTimeoutException``, raised wherever the job is) says so even where a step turned
    it into its own error (a reader's "could not be read").

    Example:
        >>> failure_reason(ValueError("reconstruct: no included slice has any pixel inside its mask"))
        'reconstruct: no included slice has any pixel inside its mask'
        >>> failure_reason(FileNotFoundError("/srv/data/x"))
        'internal error (FileNotFoundError); the server log has the job id'
    """
    cause: BaseException | None = exc
    for _ in range(16):                                 # the chain of causes, bounded
        if cause is None:
            break
        if type(cause).__name__ == "JobTimeoutException":
            return TIMED_OUT
        cause = cause.__cause__ or cause.__context__
    if isinstance(exc, ServiceError):
        return exc.detail
    if type(exc) is ValueError:
        return str(exc)
    return f"internal error ({type(exc).__name__}); the server log has the job id"


def _name(names: dict, field: str, index: int) -> str:
    """The client's name of an input file (for messages), from ``names.json``."""
    listed = names.get(field) or []
    return listed[index] if index < len(listed) and isinstance(listed[index], str) else f"{field}[{index}]"


def _execute(store: JobStore, folder: Path, models_dir: Path, job_id: str, progress,  # noqa: ANN001
             attempt: int, localisers_dir: Path | None = None) -> None:
    from service.pipeline.predict import stack_orders
    from service.pipeline.stack_upload import StackUpload, mask_on_stack_grid
    from service.io.limits import DecodeBudget
    from service.io.readers import read_upload
    from service.reconstruction.export import write_outputs
    from service.preprocess.stack import split_stack
    from service.reconstruction.job import bias_corrected_stacks, refine_job
    from service.pipeline.documents import stack_geometry
    from service.reconstruction.refined_poses import refined_poses_body
    from service.reconstruction.slices import SliceSet

    t0 = time.perf_counter()
    if not (folder / "inputs" / "params.json").is_file():
        raise InternalError(MISSING_UPLOADS)
    params = json.loads((folder / "inputs" / "params.json").read_text())
    kept = decoded_files(folder / "inputs")
    files = kept or _stack_files(folder / "inputs")     # files as sent: a job queued by an earlier version
    orders = per_stack([SliceOrder.parse(t) for t in params.get("slice_order") or []], len(files))
    thickness = params.get("slice_thickness_mm") or [None] * len(files)       # the client's word over the file's
    progress("reading", 0.02)
    uploads = []
    names_path = folder / "inputs" / "names.json"
    names = json.loads(names_path.read_text()) if names_path.exists() else {}
    # The files passed the limits when they were submitted: re-read without a budget of their own.
    budget = DecodeBudget(2**62)
    for i, (s, m) in enumerate(files):
        sname = _name(names, "stacks", i)
        mname = _name(names, "masks", i) if m is not None else None
        if kept:
            vol, mask = load_volume(s), None if m is None else load_volume(m)
        else:
            vol = read_upload(s, sname, budget=budget.file(sname), scratch=s.parent)
            mask = (read_upload(m, mname, budget=budget.file(mname), scratch=m.parent, magnitudes=False)
                    if m is not None else None)
        if thickness[i] is not None:
            vol = replace(vol, slice_thickness_mm=float(thickness[i]))
        uploads.append(mask_on_stack_grid(StackUpload(sname, vol, mask, mname,
                                                      mask_holds_csf=bool(params.get("masks_hold_csf", False)))))
    poses_path = folder / "inputs" / "poses.json"
    localiser = job_localiser(localisers_dir, uploads)
    model_file = models_dir / params.get("model", "default") / "model.onnx"
    if poses_path.exists():
        counts = [u.volume.array.shape[u.slice_axis] for u in uploads]
        body = json.loads(poses_path.read_text())
        poses = poses_from_predict_body(body, counts, [u.volume.affine for u in uploads])
        estimator, plane = job_estimator(model_file, required=False, sha256=params.get("model_sha256"))
        if estimator is not None:       # the job's own model (its frame steps, its report), not the earlier request's
            body["model"] = estimator.info.reference(params.get("model", "default"))
        masks = uploaded_pose_masks(uploads, localiser)
        if any(u.localised for u in uploads) and not any(m.any() for m in masks):
            raise UnusableImage(NO_BRAIN_FOUND)       # not the reconstruction's "no pixel inside its mask"
        poses, started_from = uploaded_start(body, poses)
    else:
        progress("predicting poses", 0.05)
        estimator, plane = job_estimator(model_file, sha256=params.get("model_sha256"))
        body, masks = predicted_body(uploads, estimator, int(params.get("mc_samples", 100)),
                                     params.get("variance_threshold"), orders, params.get("max_expected_error_mm"),
                                     localiser, model_name=params.get("model", "default"))
        poses, started_from = own_start(body)
    progress("reconstructing", 0.15)
    known_orders = stack_orders(orders, uploads)
    volumes = bias_corrected_stacks([u.volume for u in uploads], masks)
    stack_inputs = [(v, m, mats, acc) for v, m, (mats, acc) in zip(volumes, masks, poses)]
    slice_set = SliceSet.from_stacks(stack_inputs)

    def refining(stage: str, fraction: float) -> None:
        if stage != "done":              # the paths' end; the job is done once it has succeeded
            progress(stage, 0.15 + 0.8 * fraction)

    job = refine_job(slice_set, stack_inputs, expected_errors(body), estimator=estimator, plane_x_mm=plane,
                     resolution_mm=float(params.get("resolution_mm", 0.8)),
                     svr_iterations=int(params.get("svr_iterations", 3)), orders=known_orders,
                     frame_steps=params.get("atlas_frame", True), mc_samples=int(params.get("mc_samples", 100)),
                     progress=refining, frame_error_mm=frame_added_mm(body))
    result, left_out = job.result, job.left_out
    if started_from != "uploaded_poses":        # uploaded poses keep the client's flags
        result.exclusion_reason = lost_reasons(result.exclusion_reason, body)
    progress("writing", 0.97)
    # The report's timings: the winning path's stages and ``total``, every path's (``all_paths``), and
    # the job's up to the writing of its outputs (``job``: prediction and the frame steps included).
    result.timings = {**result.timings, "job": time.perf_counter() - t0}
    extra = {"started_from": started_from, **job.report(),
             "provenance": provenance(body.get("model"), uploads, localiser, bool(params.get("masks_hold_csf", False)))}
    report = write_outputs(result, slice_set, folder / "outputs", extra=extra, more_files=("poses.json",),
                           stack_headers=[u.volume.nifti for u in uploads])
    slice_frames = [split_stack(u.volume, np.ones(u.volume.array.shape, bool)).slice_from_voxel for u in uploads]
    refined = refined_poses_body(body, result.atlas_from_voxel_final, slice_frames, included=result.included,
                                 weight=result.slice_weight, ncc=result.ncc, held_out_ncc=result.held_out_ncc,
                                 reasons=result.exclusion_reason, job_id=job_id,
                                 placed_by_stack_motion=left_out.moved, placed_by_volume=left_out.registered,
                                 refined_expected_error_mm=job.expected_error_mm)
    for i, (stack, u) in enumerate(zip(refined.get("stacks", []), uploads)):
        # Results are kept until the retention limit; the clients' file names (often patient names)
        # are not: a stack is named by its place in the upload. Its geometry is the upload's as the
        # service read it (uploaded poses need not carry it; `svrnet export` cuts slices by it).
        stack.update(stack_geometry(i, f"stacks[{i}]", u.volume, u.slice_axis))
    (folder / "outputs" / "poses.json").write_text(json.dumps(refined))
    if not store.finish(job_id, report, attempt):
        if not store.is_cancelled(job_id):
            raise Superseded
        shutil.rmtree(folder, ignore_errors=True)    # cancelled while writing: leave nothing behind
        raise Cancelled
