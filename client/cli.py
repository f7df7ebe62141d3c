"""``svrnet``: the SVRnet command line (HTTP API v1 client).

Commands::

    svrnet predict STACK... [--mask M...] [--out poses.json] [--mc-samples N] [--threshold T]
                            [--no-bias-correction] [--model NAME] [--transforms-out transforms.zip]
    svrnet masks STACK... --out-dir DIR [--margin-mm MM]
    svrnet reconstruct STACK... [--mask M...] [--poses poses.json] [--resolution 0.8] [--svr-iterations 3]
                       [--wait] [--out recon.nii.gz] [--preview preview.png] [--poses-out refined.json]
    svrnet fetch JOB [--out recon.nii.gz] [--preview preview.png] [--poses-out refined.json]
    svrnet stream STACK... [--mask M...] [--pace SECONDS] [--slice-order ORDER]
                           [--mc-samples N] [--max-expected-error MM] [--json-out messages.jsonl]
    svrnet status JOB
    svrnet cancel JOB
    svrnet models
    svrnet export ANSWER.json STACK... --to nesvor|niftymic --out-dir DIR [--mask M...]

Every command takes ``--server URL`` (default ``$SVRNET_SERVER``, else ``http://127.0.0.1:8000``); the
API key comes from ``$SVRNET_API_KEY`` (sent as ``Authorization: Bearer``); ``$SVRNET_TIMEOUT`` sets the
read/write timeout in seconds (default 300).

Exit codes:
    0   success
    1   unexpected error (e.g. a local file could not be written)
    2   usage error (bad option or argument: typer's own, or the client's check naming it)
    3   connection failed (server unreachable, timeout)
    4   unauthorized (missing or wrong API key; a browser Origin the server does not allow)
    5   bad input (400, 413, 415, 422: malformed request, too large, unreadable or unusable file; every
        slice of a stream refused)
    6   not found (unknown model or job)
    7   busy (429/503/507 after every retry)
    8   job failed or cancelled
    9   server error (5xx)
    10  conflict (409, e.g. result asked for before the job succeeded; a submission's idempotency key that
        the server holds for another request)
    11  timed out waiting for a job (the job goes on)
    12  nothing usable in the answer, its files written: no slice accepted (predict, stream), a volume whose
        stacks do not predict each other (reconstruct)
    130 interrupted (Ctrl-C); a job already submitted goes on on the server

Errors are one red line on stderr with the server's problem detail (and request id), never a traceback.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Optional

import httpx
import typer

from client._client import DEFAULT_SERVER, SVRnetClient
from client.cli_export import export
from client.cli_stream import stream
from client.cli_support import (DEFAULT_VOLUME, DELETE_HELP, ApiKeyOpt, BiasCorrectionOpt, DeleteOpt, JobArg, MaskOpt,
                                MasksHoldCsfOpt, OverwriteOpt, MaxExpectedOpt, McSamplesOpt, ModelOpt, ServerOpt,
                                STACK_SPACE_HELP, StackSpaceOpt, StacksArg, ThresholdOpt, check_folder_writable,
                                check_masks, check_writable, follow_job, job_id_of,
                                once_or_per_stack, resolution_range, slice_order_words, timeout_from_env, user_path,
                                volume_path, write_json, write_results)
from client.errors import ArgumentError, NotFound, SVRnetError
from client.exits import (EXIT_HELP, EXIT_JOB_FAILED, EXIT_NOTHING_USABLE, EXIT_USAGE, errors, fail,
                          job_goes_on, stderr, stdout, submitting)
from client.job_views import job_table, quality_line, refined_poses_line
from client.launch import installed_version
from client.mask_archive import masks_already_there
from client.transport import new_idempotency_key, server_address
from client.views import masks_table, models_table, predict_hints, summarise, upload_bar, usable

app = typer.Typer(
    name="svrnet",
    help="SVRnet client: slice-to-atlas poses (predict) and reconstructions of fetal MRI stacks.\n\n"
         "Server: --server or $SVRNET_SERVER (default http://127.0.0.1:8000); API key: $SVRNET_API_KEY; "
         "$SVRNET_TIMEOUT: seconds a call may wait between two bytes as the server reads or answers it (default "
         "300; a status call 30); $SVRNET_CA_BUNDLE: your site's CA certificates, for an https:// server whose "
         "certificate this machine does not trust.",
    epilog=EXIT_HELP,
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,            # click's plain help: option names whole at any width (rich's panels cut them)
)


def _print_version(asked: bool) -> None:
    if asked:
        print(f"svrnet {installed_version() or '(not installed: run from a folder)'}")
        raise typer.Exit()


@app.callback()
def _options(version: Annotated[bool, typer.Option(
        "--version", is_eager=True, callback=_print_version,
        help="print the client's version and exit")] = False) -> None:
    """The options every command shares (none but ``--version``)."""


def make_client(server: str, api_key: str | None) -> SVRnetClient:
    """The client every command uses (tests monkeypatch this factory); a URL that is no URL is a usage
    error naming ``--server`` (the client's :func:`~client.transport.server_address`, or httpx's)."""
    try:
        server_address(server)
    except ArgumentError as exc:
        raise typer.BadParameter(str(exc).removeprefix("server: "), param_hint="--server") from None
    try:
        return SVRnetClient(base_url=server, api_key=api_key, timeout=timeout_from_env())
    except httpx.InvalidURL as exc:
        raise typer.BadParameter(f"{server!r}: {exc}", param_hint="--server") from None


@contextmanager
def _client(server: str, api_key: str | None) -> Iterator[SVRnetClient]:
    svr = make_client(server, api_key or None)
    try:
        yield svr
    finally:
        svr.close()


@app.command(epilog=EXIT_HELP)
def predict(
    stacks: StacksArg,
    mask: MaskOpt = None,
    server: ServerOpt = DEFAULT_SERVER,
    api_key: ApiKeyOpt = None,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", dir_okay=False, callback=user_path,
                                                help="write the full JSON answer here")] = None,
    mc_samples: McSamplesOpt = None,
    threshold: ThresholdOpt = None,
    max_expected_error: MaxExpectedOpt = None,
    bias_correction: BiasCorrectionOpt = True,
    model: ModelOpt = None,
    slice_order: Annotated[Optional[list[str]], typer.Option(
        callback=slice_order_words,
        help="acquisition order, once for every stack or once per stack: interleaved, sequential, "
             "interleaved-even-first, interleaved-odd-first, or slice indices as acquired (0,2,4,1,3); "
             "default: the server's motion model chooses")] = None,
    stack_consistency: Annotated[bool, typer.Option(
        "--stack-consistency/--no-stack-consistency",
        help="decide each stack's left-right branch from all its slices and fit its motion model "
             "(off: every slice alone, its branch undecided; image consistency needs it)")] = True,
    image_consistency: Annotated[bool, typer.Option(
        "--image-consistency/--no-image-consistency",
        help="refine the poses where slices of different stacks cross")] = True,
    masks_hold_csf: MasksHoldCsfOpt = False,
    transforms_out: Annotated[Optional[Path], typer.Option(
        "--transforms-out", dir_okay=False, callback=user_path,
        help="also write each slice's ITK transform here (.zip of .tfm files, laid out as a job's)")] = None,
    overwrite: OverwriteOpt = False,
) -> None:
    """Atlas pose and confidence of every slice of every stack (POST /v1/predict)."""
    check_masks(stacks, mask, masks_hold_csf)
    once_or_per_stack(slice_order, stacks, "--slice-order")
    check_writable(overwrite, out=out, transforms_out=transforms_out)
    err = stderr()
    with errors(), _client(server, api_key) as svr:
        with upload_bar(err, f"{len(stacks)} stack(s)") as progress:
            result = svr.predict(stacks, mask, mc_samples=mc_samples, variance_threshold=threshold,
                                 max_expected_error_mm=max_expected_error,
                                 bias_correction=None if bias_correction else False, model=model,
                                 slice_order=slice_order, stack_consistency=None if stack_consistency else False,
                                 image_consistency=None if image_consistency else False,
                                 masks_hold_csf=True if masks_hold_csf else None, progress=progress)
        if out is not None:                 # the files first: a closed pipe on stdout loses no answer
            write_json(out, result)
        if transforms_out is not None:
            from client.slice_transforms import write_transforms_zip       # numpy: only where it is needed
            write_transforms_zip(result, transforms_out)
        console = stdout()
        console.print(summarise(result))
        stage_off = ("the stack consistency stage" if not stack_consistency else
                     None if image_consistency else "the image consistency stage")
        for hint in predict_hints(result, stage_off):
            console.print(hint, style="yellow", markup=False)
        total = (result.get("timing_ms") or {}).get("total")
        console.print(f"request {result.get('request_id', '?')}"
                      + (f" · {total / 1e3:.2f} s on the server" if isinstance(total, (int, float)) else ""))
        for written in (out, transforms_out):
            if written is not None:
                console.print(f"wrote {written}")
    if not usable(result):
        raise typer.Exit(EXIT_NOTHING_USABLE)


@app.command(epilog=EXIT_HELP)
def masks(
    stacks: StacksArg,
    out_dir: Annotated[Path, typer.Option("--out-dir", "-o", file_okay=False, callback=user_path,
                                          help="where the masks are written")],
    server: ServerOpt = DEFAULT_SERVER,
    api_key: ApiKeyOpt = None,
    model: Annotated[Optional[str], typer.Option(help="localiser name (default: the server's)")] = None,
    margin: Annotated[Optional[float], typer.Option(
        "--margin-mm", min=0, max=20, help="grow each mask outward by this many mm (the masks are the skull's inside; "
        "2-4 mm reaches masks drawn to its outer edge)")] = None,
    overwrite: Annotated[bool, typer.Option(
        "--overwrite", help="replace files of the same names in --out-dir (without it they are kept and nothing "
        "is written)")] = False,
) -> None:
    """Brain masks of stacks as they leave the scanner (POST /v1/masks): one NIfTI per stack."""
    check_folder_writable("out_dir", out_dir)
    there = [] if overwrite else masks_already_there(stacks, out_dir)
    if there:
        fail(f"out_dir: {out_dir} holds {', '.join(there)} already; nothing was sent (--overwrite replaces them)",
             EXIT_USAGE)
    err = stderr()
    with errors(), _client(server, api_key) as svr:
        with upload_bar(err, f"{len(stacks)} stack(s)") as progress:
            report = svr.masks(stacks, out_dir, model=model, margin_mm=margin, progress=progress, overwrite=overwrite)
        stdout().print(masks_table(report, out_dir))


@app.command(epilog=EXIT_HELP)
def reconstruct(
    stacks: StacksArg,
    mask: MaskOpt = None,
    server: ServerOpt = DEFAULT_SERVER,
    api_key: ApiKeyOpt = None,
    poses: Annotated[Optional[Path], typer.Option(
        exists=True, dir_okay=False, readable=True,
        help="JSON answer of `svrnet predict --out` for these files")] = None,
    resolution: Annotated[Optional[float], typer.Option(
        "--resolution", callback=resolution_range,
        help="output spacing in mm, over 0.2 and at most 5 (server default 0.8)")] = None,
    svr_iterations: Annotated[Optional[int], typer.Option(min=0, max=10,
                                                          help="SVR iterations (server default 3; 0: none, the volume at the poses the job starts from)")] = None,
    mc_samples: McSamplesOpt = None,
    threshold: ThresholdOpt = None,
    max_expected_error: MaxExpectedOpt = None,
    wait: Annotated[bool, typer.Option("--wait", help="wait for the job and download its results")] = False,
    out: Annotated[Optional[Path], typer.Option(
        "--out", "-o", dir_okay=False, callback=volume_path,
        help="volume file, .nii.gz or .nii (uncompressed) (implies --wait; default recon.nii.gz with --wait)")] = None,
    preview: Annotated[Optional[Path], typer.Option(
        dir_okay=False, callback=user_path, help="also download the preview PNG here (implies --wait)")] = None,
    poses_out: Annotated[Optional[Path], typer.Option(
        "--poses-out", dir_okay=False, callback=user_path,
        help="also write the refined slice poses (/v1/predict schema) here (implies --wait)")] = None,
    transforms_out: Annotated[Optional[Path], typer.Option(
        "--transforms-out", dir_okay=False, callback=user_path,
        help="also download the per-slice ITK transforms (.zip of .tfm files) here (implies --wait)")] = None,
    stack_space: Annotated[Optional[int], typer.Option(
        "--stack-space", min=0, help=STACK_SPACE_HELP + " (implies --wait)")] = None,
    delete: Annotated[bool, typer.Option("--delete", help=DELETE_HELP + " (implies --wait)")] = False,
    timeout: Annotated[float, typer.Option(min=0, help="seconds to wait for the job")] = 3600.0,
    poll: Annotated[float, typer.Option(min=0.05, help="seconds between status polls")] = 1.0,
    slice_order: Annotated[Optional[list[str]], typer.Option(
        callback=slice_order_words,
        help="acquisition order, once for every stack or once per stack (as for predict)")] = None,
    atlas_frame: Annotated[bool, typer.Option("--atlas-frame/--no-atlas-frame",
                                              help="re-estimate the volume's atlas frame with the model")] = True,
    masks_hold_csf: MasksHoldCsfOpt = False,
    thickness: Annotated[Optional[list[float]], typer.Option(
        "--thickness", help="slice thickness in mm, once for every stack or once per stack (default: a DICOM "
        "file's SliceThickness, else the slice spacing; give it for slices with gaps or overlap)")] = None,
    model: ModelOpt = None,
    overwrite: OverwriteOpt = False,
    idempotency_key: Annotated[Optional[str], typer.Option(
        "--idempotency-key", help="the submission's key, 8 to 200 printable ASCII characters (default: a new "
        "one): the same command sent again with the key an earlier run named gets that job, not a second "
        "one")] = None,
    as_json: Annotated[bool, typer.Option(
        "--json", help="print the submission as JSON (job_id, status, status_url, idempotency_key) instead of "
        "words, for a script; not with --wait (then: svrnet status JOB --json)")] = False,
) -> None:
    """Start a reconstruction job (POST /v1/reconstructions); with --wait, follow it and download the volume."""
    check_masks(stacks, mask, masks_hold_csf)
    once_or_per_stack(thickness, stacks, "--thickness")
    once_or_per_stack(slice_order, stacks, "--slice-order")
    if stack_space is not None and stack_space >= len(stacks):
        fail(f"--stack-space: {stack_space} is not one of the {len(stacks)} stacks given (0-{len(stacks) - 1})",
             EXIT_USAGE)
    wait = wait or delete or any(p is not None for p in (out, preview, poses_out, transforms_out, stack_space))
    if as_json and wait:
        fail("--json prints the submission and returns: not with --wait or an output option (follow the job with "
             "svrnet status JOB --json)", EXIT_USAGE)
    check_writable(overwrite, out=out if out is not None or not wait else DEFAULT_VOLUME, preview=preview,
                   poses_out=poses_out, transforms_out=transforms_out)
    err, console = stderr(), stdout()
    key = idempotency_key or new_idempotency_key()
    with errors(), _client(server, api_key) as svr:
        with upload_bar(err, f"{len(stacks)} stack(s)") as progress, submitting(key):
            job = svr.reconstruct(stacks, mask, poses, resolution_mm=resolution, svr_iterations=svr_iterations,
                                  mc_samples=mc_samples, variance_threshold=threshold,
                                  max_expected_error_mm=max_expected_error, slice_order=slice_order,
                                  atlas_frame=None if atlas_frame else False,
                                  masks_hold_csf=True if masks_hold_csf else None, slice_thickness_mm=thickness,
                                  model=model, progress=progress, idempotency_key=key)
        job_id = str(job.get("job_id", ""))
        if as_json:
            sys.stdout.write(json.dumps({**job, "idempotency_key": key}, indent=2) + "\n")   # plain, as status's
            return
        console.print(f"job {job_id} {job.get('status', 'queued')}: {job.get('status_url', '')}", soft_wrap=True)
        if not wait:
            console.print(f"follow it with: svrnet status {job_id}; download it with: svrnet fetch {job_id}")
            return
        incoherent = follow_and_write(svr, job_id, poll, timeout, out, preview, poses_out, transforms_out, stack_space,
                                      delete)
    if incoherent:
        raise typer.Exit(EXIT_NOTHING_USABLE)


def follow_and_write(svr: SVRnetClient, job_id: str, poll: float, timeout: float, out: Path | None,
                     preview: Path | None, poses_out: Path | None, transforms_out: Path | None,
                     stack_space: int | None, delete: bool = False) -> bool:
    """Wait for a job, then download its results (:func:`write_results`; True: no coherent brain), a
    Ctrl-C in either told as what it leaves on the server (:func:`~client.exits.job_goes_on`); then,
    with ``delete``, delete the job on the server, else say until when the server keeps it."""
    with job_goes_on(job_id):
        done = follow_job(svr, job_id, poll, timeout)
    with job_goes_on(job_id, succeeded=True):
        incoherent = write_results(svr, job_id, done, out, preview, poses_out, transforms_out, stack_space)
    if delete:
        try:
            svr.cancel(job_id)
        except (SVRnetError, KeyboardInterrupt) as exc:     # the files are written: the command's answer stands
            why = "interrupted" if isinstance(exc, KeyboardInterrupt) else str(exc)
            stderr().print(f"the results are written, but the job could not be deleted on the server ({why}): "
                           f"svrnet cancel {job_id} deletes it", markup=False)
        else:
            stdout().print(f"deleted job {job_id} and its results on the server")
    else:
        until = f" until {done['expires_at']}" if done.get("expires_at") else ""
        stdout().print(f"the server keeps the job's results{until}; svrnet cancel {job_id} deletes them now",
                       markup=False)
    return incoherent


@app.command(epilog=EXIT_HELP)
def fetch(
    job: JobArg,
    server: ServerOpt = DEFAULT_SERVER,
    api_key: ApiKeyOpt = None,
    out: Annotated[Optional[Path], typer.Option(
        "--out", "-o", dir_okay=False, callback=volume_path,
        help="volume file, .nii.gz or .nii (uncompressed) (default recon.nii.gz)")] = None,
    preview: Annotated[Optional[Path], typer.Option(dir_okay=False, callback=user_path,
                                                    help="also download the preview PNG here")] = None,
    poses_out: Annotated[Optional[Path], typer.Option(
        "--poses-out", dir_okay=False, callback=user_path,
        help="also write the refined slice poses (/v1/predict schema) here")] = None,
    transforms_out: Annotated[Optional[Path], typer.Option(
        "--transforms-out", dir_okay=False, callback=user_path,
        help="also download the per-slice ITK transforms (.zip of .tfm files) here")] = None,
    stack_space: StackSpaceOpt = None,
    delete: DeleteOpt = False,
    timeout: Annotated[float, typer.Option(min=0, help="seconds to wait for a job still running")] = 3600.0,
    poll: Annotated[float, typer.Option(min=0.05, help="seconds between status polls")] = 1.0,
    overwrite: OverwriteOpt = False,
) -> None:
    """Download a job's results (GET /v1/reconstructions/{job}/...), waiting for it first if it is still
    queued or running: what `reconstruct --wait` does, for a job started without it."""
    job = job_id_of(job)
    check_writable(overwrite, out=out if out is not None else DEFAULT_VOLUME, preview=preview, poses_out=poses_out,
                   transforms_out=transforms_out)
    with errors(), _client(server, api_key) as svr:
        incoherent = follow_and_write(svr, job, poll, timeout, out, preview, poses_out, transforms_out, stack_space,
                                      delete)
    if incoherent:
        raise typer.Exit(EXIT_NOTHING_USABLE)


app.command(name="stream", epilog=EXIT_HELP)(stream)     # svrnet stream: client/cli_stream.py


@app.command(epilog=EXIT_HELP)
def status(
    job: JobArg,
    server: ServerOpt = DEFAULT_SERVER,
    api_key: ApiKeyOpt = None,
    as_json: Annotated[bool, typer.Option("--json", help="print the raw JSON")] = False,
) -> None:
    """Status of a reconstruction job (GET /v1/reconstructions/{job}); exit 8 when it failed or was
    cancelled, as for `reconstruct --wait`."""
    job = job_id_of(job)
    with errors(), _client(server, api_key) as svr:
        state = svr.status(job)
        console = stdout()
        if as_json:
            sys.stdout.write(json.dumps(state, indent=2) + "\n")        # plain: no colour codes, even with FORCE_COLOR
        else:
            console.print(job_table(state, job))
            report = state.get("report") or {}                # a finished job: how to judge its volume
            for line in (quality_line(report.get("quality"), report.get("n_stacks")),
                         refined_poses_line(report.get("refined_poses"))):
                if line:
                    console.print(line, markup=False)
    if state.get("status") in ("failed", "cancelled"):
        raise typer.Exit(EXIT_JOB_FAILED)


@app.command(epilog=EXIT_HELP)
def cancel(
    job: JobArg,
    server: ServerOpt = DEFAULT_SERVER,
    api_key: ApiKeyOpt = None,
) -> None:
    """Cancel a queued or running job and delete its files; a finished (or cancelled) job is deleted
    (DELETE /v1/reconstructions/{job})."""
    job = job_id_of(job)
    with errors(), _client(server, api_key) as svr:
        before = str(svr.status(job).get("status", ""))
        svr.cancel(job)
        if before in ("queued", "running"):
            try:
                cancelled = svr.status(job).get("status") == "cancelled"
            except NotFound:              # it ended between the two calls: the server deleted it, results and all
                cancelled = False
            stdout().print(f"job {job} cancelled" if cancelled else
                           f"job {job} had ended before the cancel arrived: deleted with its results")
        else:
            stdout().print(f"job {job} ({before}) deleted")


@app.command(epilog=EXIT_HELP)
def models(
    server: ServerOpt = DEFAULT_SERVER,
    api_key: ApiKeyOpt = None,
    as_json: Annotated[bool, typer.Option("--json", help="print the raw JSON")] = False,
) -> None:
    """Models the server offers (GET /v1/models)."""
    with errors(), _client(server, api_key) as svr:
        listed = svr.models()
        console = stdout()
        if as_json:
            sys.stdout.write(json.dumps(listed, indent=2) + "\n")
            return
        console.print(models_table(listed))


app.command(name="export", epilog=EXIT_HELP)(export)


if __name__ == "__main__":  # pragma: no cover
    app()
