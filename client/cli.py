"""``svrnet``: the SVRnet command line (HTTP API v1 client).

Commands::

    svrnet predict STACK... [--mask M...] [--out poses.json] [--mc-samples N] [--threshold T]
                            [--no-bias-correction] [--model NAME]
    svrnet reconstruct STACK... [--mask M...] [--poses poses.json] [--resolution 0.8] [--svr-iterations 3]
                       [--poses-out refined.json]
                                [--wait] [--out recon.nii.gz] [--preview preview.png]
    svrnet stream STACK... [--mask M...] [--pace SECONDS] [--order sequential|interleaved]
                           [--mc-samples N] [--max-expected-error MM] [--json-out messages.jsonl]
    svrnet status JOB
    svrnet cancel JOB
    svrnet models

Every command takes ``--server URL`` (default ``$SVRNET_SERVER``, else ``http://127.0.0.1:8000``); the
API key comes from ``$SVRNET_API_KEY`` (sent as ``Authorization: Bearer``); ``$SVRNET_TIMEOUT`` sets the
read/write timeout in seconds (default 300).

Exit codes:
    0   success
    1   unexpected error (e.g. a local file could not be written)
    2   usage error (bad option or argument; typer's own)
    3   connection failed (server unreachable, timeout)
    4   unauthorized (missing or wrong API key)
    5   bad input (400, 413, 415, 422: malformed request, too large, unreadable or unusable file)
    6   not found (unknown model or job)
    7   busy (429/503 after every retry)
    8   job failed or cancelled
    9   server error (5xx)
    10  conflict (409, e.g. result asked for before the job succeeded)
    11  timed out waiting for a job (the job goes on)

Errors are one red line on stderr with the server's problem detail (and request id), never a traceback.
"""

from __future__ import annotations

import json
import os
import statistics
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Optional

import httpx
import typer
from rich import box
from rich.console import Console
from rich.progress import (BarColumn, DownloadColumn, Progress, SpinnerColumn, TaskProgressColumn, TextColumn,
                           TimeElapsedColumn, TransferSpeedColumn)
from rich.live import Live
from rich.table import Table

from client._client import DEFAULT_SERVER, SVRnetClient
from client.errors import (BadRequest, Busy, Conflict, ConnectionFailed, JobFailed, NotFound, PayloadTooLarge,
                           ServerError, SVRnetError, Unauthorized, UnsupportedFile, UnusableInput, WaitTimeout)

if TYPE_CHECKING:                     # client.stream needs numpy and nibabel: imported by `svrnet stream` only
    from client.stream import Sent

EXIT_OK, EXIT_UNEXPECTED, EXIT_USAGE = 0, 1, 2
EXIT_CONNECTION, EXIT_UNAUTHORIZED, EXIT_BAD_INPUT, EXIT_NOT_FOUND = 3, 4, 5, 6
EXIT_BUSY, EXIT_JOB_FAILED, EXIT_SERVER, EXIT_CONFLICT, EXIT_TIMEOUT = 7, 8, 9, 10, 11

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
    "Exit codes: 0 ok · 1 unexpected error · 2 usage · 3 connection failed · 4 unauthorized · "
    "5 bad input (400/413/415/422) · 6 not found · 7 busy (429/503 after retries) · "
    "8 job failed/cancelled · 9 server error (5xx) · 10 conflict (409) · 11 timed out waiting."
)

app = typer.Typer(
    name="svrnet",
    help="SVRnet client: slice-to-atlas poses (predict) and reconstructions of fetal MRI stacks.\n\n"
         "Server: --server or $SVRNET_SERVER (default http://127.0.0.1:8000); API key: $SVRNET_API_KEY.",
    epilog=EXIT_HELP,
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def make_client(server: str, api_key: str | None) -> SVRnetClient:
    """The client every command uses (tests monkeypatch this factory)."""
    return SVRnetClient(base_url=server, api_key=api_key, timeout=_timeout())


def _timeout() -> httpx.Timeout:
    """Read/write timeout from ``$SVRNET_TIMEOUT`` (seconds; default 300): a large request on a CPU
    server can take longer."""
    raw = os.environ.get("SVRNET_TIMEOUT", "300")
    try:
        seconds = float(raw)
    except ValueError:
        seconds = -1.0
    if not seconds > 0:
        raise typer.BadParameter(f"SVRNET_TIMEOUT={raw!r}: must be a number of seconds > 0")
    return httpx.Timeout(connect=5.0, read=seconds, write=seconds, pool=5.0)


def _check_writable(*paths: Path | None) -> None:
    """Output files must be writable BEFORE anything is uploaded (not after an hour of reconstruction)."""
    for path in paths:
        if path is None:
            continue
        folder = path.expanduser().resolve().parent
        if not folder.is_dir() or not os.access(folder, os.W_OK):
            raise typer.BadParameter(f"{path}: its folder {folder} does not exist or is not writable",
                                     param_hint="--out/--preview")


def _job_id(job: str) -> str:
    if not job.strip():
        raise typer.BadParameter("the job id is empty", param_hint="JOB")
    return job.strip()


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


def _stdout() -> Console:
    return Console(highlight=False)


def _stderr() -> Console:
    return Console(stderr=True, highlight=False)


def _fail(message: str, code: int) -> None:
    _stderr().print(f"error: {message}", style="bold red", markup=False, soft_wrap=True)
    raise typer.Exit(code)


@contextmanager
def _errors() -> Iterator[None]:
    """Client errors -> one red line on stderr and the documented exit code; never a traceback."""
    try:
        yield
    except (typer.Exit, typer.Abort, typer.BadParameter):   # typer's own ending: its exit code stands
        raise
    except SVRnetError as e:
        _fail(" ".join(str(e).split()), exit_code_for(e))
    except KeyboardInterrupt:
        _fail("interrupted", 130)
    except OSError as e:
        _fail(f"{type(e).__name__}: {e}", EXIT_UNEXPECTED)
    except Exception as e:  # noqa: BLE001 - the CLI promises no tracebacks
        _fail(f"unexpected {type(e).__name__}: {e}", EXIT_UNEXPECTED)


@contextmanager
def _client(server: str) -> Iterator[SVRnetClient]:
    svr = make_client(server, os.environ.get("SVRNET_API_KEY") or None)
    try:
        yield svr
    finally:
        svr.close()


@contextmanager
def _upload_bar(console: Console, label: str) -> Iterator[Callable[[int, int], None]]:
    """A rich progress bar fed by ``progress(bytes_sent, total)``; shows 'processing' once sent."""
    with Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), DownloadColumn(),
                  TransferSpeedColumn(), TimeElapsedColumn(), console=console, transient=True,
                  disable=not console.is_terminal) as bar:
        task = bar.add_task(f"uploading {label}", total=None)

        def update(sent: int, total: int) -> None:
            done = sent >= total
            bar.update(task, completed=sent, total=total,
                       description="waiting for the server" if done else f"uploading {label}")

        yield update


def _check_masks(stacks: list[Path], masks: list[Path] | None) -> None:
    if masks and len(masks) != len(stacks):
        raise typer.BadParameter(f"{len(masks)} masks for {len(stacks)} stacks; give none or one per stack",
                                 param_hint="--mask")


def _positive(value: float | None) -> float | None:
    if value is not None and not value > 0:
        raise typer.BadParameter("must be > 0")
    return value


def _write_json(path: Path, body: Any) -> None:
    path.write_text(json.dumps(body, indent=2) + "\n")


NAME_WIDTH = 18
"""Stack file names up to this long stay on one line of the summary table; longer ones fold, so that
every column fits an 80-column terminal."""


def summarise(result: dict[str, Any]) -> Table:
    """The per-stack summary table of a ``/v1/predict`` body."""
    model = result.get("model") or {}
    limit, threshold = result.get("max_expected_error_mm"), result.get("variance_threshold")
    title = (f"model {model.get('name', '?')} {model.get('version', '')} · mc_samples {result.get('mc_samples')} · "
             f"accepted: expected error <= {'-' if limit is None else f'{limit:.3g} mm'}, "
             f"variance <= {'-' if threshold is None else f'{threshold:.4g}'}")
    table = Table(title=title, title_justify="left", caption_justify="left", box=box.SIMPLE_HEAD, pad_edge=False,
                  collapse_padding=True,
                  caption="brain: the uploaded mask, or the volume the localiser found (its confidence); "
                          "expected error, variance: the stack's medians")
    stacks = result.get("stacks") or []
    longest = max([len(str(s.get("filename", ""))) for s in stacks] + [5])
    for col, just in (("stack", "left"), ("brain", "left"), ("accepted", "right"), ("rejected (by reason)", "left"),
                      ("expected error", "right"), ("variance", "right")):
        # names up to NAME_WIDTH stay whole (the other columns wrap first), longer ones fold; no cell is cut short
        table.add_column(col, justify=just, overflow="fold", no_wrap=col == "stack" and longest <= NAME_WIDTH,  # type: ignore[arg-type]
                         min_width={"stack": min(longest, NAME_WIDTH), "rejected (by reason)": 19}.get(col),
                         max_width=None if col in ("stack", "rejected (by reason)") else 8)
    for stack in stacks:
        slices = stack.get("slices") or []
        accepted = sum(1 for s in slices if s.get("accepted"))
        reasons = Counter(s.get("reason") or "unknown" for s in slices if not s.get("accepted"))
        variances = [s["geodesic_variance"] for s in slices if s.get("geodesic_variance") is not None]
        expected = [s["expected_error_mm"] for s in slices if s.get("expected_error_mm") is not None]
        where = stack.get("localisation") or {}
        brain = "mask" if where.get("method") == "mask" else \
            f"{where.get('brain_volume_ml', 0):.0f} ml ({where.get('confidence', 0):.2f})" if where else "-"
        table.add_row(str(stack.get("filename", "")), brain, f"{accepted} of {len(slices)}",
                      ", ".join(f"{k} {v}" for k, v in sorted(reasons.items())) or "-",
                      f"{statistics.median(expected):.1f} mm" if expected else "-",
                      f"{statistics.median(variances):.4g}" if variances else "-")
    return table


MaxExpectedOpt = Annotated[Optional[float], typer.Option(
    "--max-expected-error", callback=_positive,
    help="accept only slices whose expected error (mm) is at most this (default: the model's)")]
ServerOpt = Annotated[str, typer.Option("--server", envvar="SVRNET_SERVER", help="server URL")]
MasksHoldCsfOpt = Annotated[bool, typer.Option(
    "--masks-hold-csf", help="the masks are the skull's inside (brain and the CSF around it, as manual fetal masks "
                             "are usually drawn): the pose network sees them less their outer 2 mm")]
McSamplesOpt = Annotated[Optional[int], typer.Option(min=1, max=1000, help="MC-dropout passes per slice")]
ThresholdOpt = Annotated[Optional[float], typer.Option(
    "--threshold", callback=_positive, help="variance threshold (default: the model's)")]
BiasCorrectionOpt = Annotated[bool, typer.Option("--bias-correction/--no-bias-correction",
                                                 help="N4 bias-field correction")]
ModelOpt = Annotated[Optional[str], typer.Option(help="model name (see `svrnet models`)")]
MaskOpt = Annotated[Optional[list[Path]], typer.Option(
    "--mask", "-m", exists=True, dir_okay=False, readable=True,
    help="region-of-interest mask; repeat, one per stack in the same order (or none)")]
StacksArg = Annotated[list[Path], typer.Argument(
    exists=True, dir_okay=False, readable=True,
    help=".nii, .nii.gz, .nrrd, .mha, .dcm or .zip of a DICOM series")]


@app.command(epilog=EXIT_HELP)
def predict(
    stacks: StacksArg,
    mask: MaskOpt = None,
    server: ServerOpt = DEFAULT_SERVER,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", dir_okay=False,
                                                help="write the full JSON answer here")] = None,
    mc_samples: McSamplesOpt = None,
    threshold: ThresholdOpt = None,
    max_expected_error: MaxExpectedOpt = None,
    bias_correction: BiasCorrectionOpt = True,
    model: ModelOpt = None,
    slice_order: Annotated[Optional[list[str]], typer.Option(
        help="acquisition order, once for every stack or once per stack: interleaved, sequential, "
             "interleaved-even-first, interleaved-odd-first, or slice indices as acquired (0,2,4,1,3); "
             "default: the server's motion model chooses")] = None,
    image_consistency: Annotated[bool, typer.Option(
        "--image-consistency/--no-image-consistency",
        help="refine the poses where slices of different stacks cross")] = True,
    masks_hold_csf: MasksHoldCsfOpt = False,
) -> None:
    """Atlas pose and confidence of every slice of every stack (POST /v1/predict)."""
    _check_masks(stacks, mask)
    _check_writable(out)
    err = _stderr()
    with _errors(), _client(server) as svr:
        with _upload_bar(err, f"{len(stacks)} stack(s)") as progress:
            result = svr.predict(stacks, mask, mc_samples=mc_samples, variance_threshold=threshold,
                                 max_expected_error_mm=max_expected_error,
                                 bias_correction=None if bias_correction else False, model=model,
                                 slice_order=slice_order, image_consistency=None if image_consistency else False,
                                 masks_hold_csf=True if masks_hold_csf else None, progress=progress)
        console = _stdout()
        console.print(summarise(result))
        total = (result.get("timing_ms") or {}).get("total")
        console.print(f"request {result.get('request_id', '?')}"
                      + (f" · {total / 1e3:.2f} s on the server" if isinstance(total, (int, float)) else ""))
        if out is not None:
            _write_json(out, result)
            console.print(f"wrote {out}")


@app.command(epilog=EXIT_HELP)
def masks(
    stacks: StacksArg,
    out_dir: Annotated[Path, typer.Option("--out-dir", "-o", file_okay=False, help="where the masks are written")],
    server: ServerOpt = DEFAULT_SERVER,
    model: Annotated[Optional[str], typer.Option(help="localiser name (default: the server's)")] = None,
) -> None:
    """Brain masks of stacks as they leave the scanner (POST /v1/masks): one NIfTI per stack."""
    err = _stderr()
    with _errors(), _client(server) as svr:
        with _upload_bar(err, f"{len(stacks)} stack(s)") as progress:
            report = svr.masks(stacks, out_dir, model=model, progress=progress)
        table = Table(title=f"brain masks in {out_dir}", title_justify="left")
        for col, just in (("stack", "left"), ("mask", "left"), ("volume (ml)", "right"), ("confidence", "right"),
                          ("slices with brain", "right")):
            table.add_column(col, justify=just)  # type: ignore[arg-type]
        for row in report.get("stacks") or []:
            table.add_row(str(row.get("filename", "")), str(row.get("mask", "")),
                          f"{row.get('brain_volume_ml', 0):.0f}", f"{row.get('confidence', 0):.2f}",
                          str(row.get("slices_with_brain", "")))
        _stdout().print(table)


def stage_label(state: dict[str, Any]) -> str:
    """The progress bar's label: the job's status and the stage it is in.

    Example:
        >>> stage_label({"status": "running", "stage": "stack registration"})
        'running: stack registration'
        >>> stage_label({"status": "queued", "stage": "queued"})
        'queued'
    """
    status, stage = state.get("status"), state.get("stage")
    return str(status) if not stage or stage == status else f"{status}: {stage}"


@app.command(epilog=EXIT_HELP)
def reconstruct(
    stacks: StacksArg,
    mask: MaskOpt = None,
    server: ServerOpt = DEFAULT_SERVER,
    poses: Annotated[Optional[Path], typer.Option(
        exists=True, dir_okay=False, readable=True,
        help="JSON answer of `svrnet predict --out` for these files")] = None,
    resolution: Annotated[Optional[float], typer.Option(
        "--resolution", callback=_positive, help="output spacing in mm (server default 0.8)")] = None,
    svr_iterations: Annotated[Optional[int], typer.Option(min=0, help="SVR iterations (server default 3)")] = None,
    mc_samples: McSamplesOpt = None,
    threshold: ThresholdOpt = None,
    max_expected_error: MaxExpectedOpt = None,
    wait: Annotated[bool, typer.Option("--wait", help="wait for the job and download its results")] = False,
    out: Annotated[Optional[Path], typer.Option(
        "--out", "-o", dir_okay=False, help="volume file (implies --wait; default recon.nii.gz with --wait)")] = None,
    preview: Annotated[Optional[Path], typer.Option(
        dir_okay=False, help="also download the preview PNG here (implies --wait)")] = None,
    poses_out: Annotated[Optional[Path], typer.Option(
        "--poses-out", dir_okay=False,
        help="also write the refined slice poses (/v1/predict schema) here (implies --wait)")] = None,
    timeout: Annotated[float, typer.Option(min=0, help="seconds to wait for the job")] = 3600.0,
    poll: Annotated[float, typer.Option(min=0.05, help="seconds between status polls")] = 1.0,
    slice_order: Annotated[Optional[list[str]], typer.Option(
        help="acquisition order, once for every stack or once per stack (as for predict)")] = None,
    atlas_frame: Annotated[bool, typer.Option("--atlas-frame/--no-atlas-frame",
                                              help="re-estimate the volume's atlas frame with the model")] = True,
    masks_hold_csf: MasksHoldCsfOpt = False,
) -> None:
    """Start a reconstruction job (POST /v1/reconstructions); with --wait, follow it and download the volume."""
    _check_masks(stacks, mask)
    _check_writable(out, preview, poses_out)
    wait = wait or out is not None or preview is not None or poses_out is not None
    err, console = _stderr(), _stdout()
    with _errors(), _client(server) as svr:
        with _upload_bar(err, f"{len(stacks)} stack(s)") as progress:
            job = svr.reconstruct(stacks, mask, poses, resolution_mm=resolution, svr_iterations=svr_iterations,
                                  mc_samples=mc_samples, variance_threshold=threshold,
                                  max_expected_error_mm=max_expected_error, slice_order=slice_order,
                                  atlas_frame=None if atlas_frame else False,
                                  masks_hold_csf=True if masks_hold_csf else None, progress=progress)
        job_id = str(job.get("job_id", ""))
        console.print(f"job {job_id} {job.get('status', 'queued')}: {job.get('status_url', '')}")
        if not wait:
            console.print(f"follow it with: svrnet status {job_id}")
            return
        with Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), TaskProgressColumn(),
                      TimeElapsedColumn(), console=err, transient=True, disable=not err.is_terminal) as bar:
            task = bar.add_task("queued", total=1.0)

            def on_progress(state: dict[str, Any]) -> None:
                label = stage_label(state)
                bar.update(task, completed=float(state.get("progress") or 0.0), description=label)

            done = svr.wait(job_id, poll_s=poll, timeout_s=timeout, on_progress=on_progress)
        target = out if out is not None else Path("recon.nii.gz")
        svr.download_volume(job_id, target)
        console.print(f"job {job_id} succeeded; wrote {target}")
        quality = quality_line((done.get("report") or {}).get("quality"))
        if quality:
            console.print(quality)
        if preview is not None:
            svr.download_preview(job_id, preview)
            console.print(f"wrote {preview}")
        if poses_out is not None:
            _write_json(poses_out, svr.refined_poses(job_id))
            console.print(f"wrote {poses_out}")


def quality_line(quality: dict[str, Any] | None) -> str:
    """The job report's ``quality`` in one line (empty when the job has none).

    Example:
        >>> quality_line({"judged_slices": 80, "median_ncc": 0.91, "fraction_ncc_above_0_7": 0.95,
        ...               "leave_one_stack_out": {"median_ncc": 0.84, "per_stack_median_ncc": [0.86, 0.8, 0.85]}})
        'quality: slices vs volume median NCC 0.91, 95% above 0.7 (80 slices); leave one stack out 0.84 (per stack 0.86, 0.80, 0.85)'
        >>> quality_line({"judged_slices": 80, "path": "slice_level", "further_passes": {"scores": [0.85, 0.86], "kept": 1}})
        'quality: slices vs volume median NCC -, - above 0.7 (80 slices); path slice_level + 1 further slice-level pass'
    """
    if not quality:
        return ""
    held = quality.get("leave_one_stack_out") or {}
    num = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
    share = quality.get("fraction_ncc_above_0_7")
    line = (f"quality: slices vs volume median NCC {num(quality.get('median_ncc'))}, "
            f"{'-' if share is None else f'{share:.0%}'} above 0.7 ({quality.get('judged_slices', 0)} slices)")
    if held.get("median_ncc") is not None:
        per = ", ".join(num(x) for x in held.get("per_stack_median_ncc") or [])
        line += f"; leave one stack out {num(held['median_ncc'])} (per stack {per})"
    if quality.get("path"):
        kept = (quality.get("further_passes") or {}).get("kept") or 0
        line += f"; path {quality['path']}"
        if kept:
            line += f" + {kept} further slice-level pass{'es' if kept > 1 else ''}"
    return line


class SendOrder(str, Enum):
    """The acquisition order ``svrnet stream`` sends a stack's slices in."""

    sequential = "sequential"
    interleaved = "interleaved"


class StreamView:
    """What ``svrnet stream`` shows: a table of the open stack's slices that grows as poses arrive
    (``renderable``, for :class:`rich.live.Live`), and, printed above it, each finished stack's table,
    a line on its acceptance and coverage, the slices of finished stacks that a later one moved, and
    the server's errors in red."""

    def __init__(self, console: Console) -> None:
        self.console = console
        self.rows: dict[tuple[str, int], dict[str, Any]] = {}    # (stack, index) -> the row's fields
        self.finished: set[str] = set()                           # stacks whose `stack` message came

    def on_message(self, message: dict[str, Any], answered: Sent | None) -> None:
        kind = message.get("type")
        if kind == "ready":
            model = message.get("model") or {}
            limit = message.get("max_expected_error_mm")
            self.console.print(f"session {message.get('session_id', '?')} · model {model.get('name', '?')} "
                               f"{model.get('version', '')} · mc_samples {message.get('mc_samples')} · accepted: "
                               f"expected error <= {'-' if limit is None else f'{limit:.3g} mm'}")
        elif kind == "pose":
            self.rows[(message.get("stack"), message.get("index"))] = {**message, "updated": False}
        elif kind == "update":
            name = message.get("stack")
            for moved in message.get("slices") or []:
                row = self.rows.setdefault((name, moved.get("index")), {"stack": name})
                row.update({k: v for k, v in moved.items() if k != "latency_ms"}, updated=True)
            if name in self.finished:
                self.console.print(f"update of stack {name}: " + ", ".join(
                    f"#{s.get('index')} {' '.join(pose_cells(s)[2:4])}" for s in message.get("slices") or []),
                    markup=False)
        elif kind == "stack":
            self.close_stack(message)
        elif kind == "error":
            about = f" ({sent_label(answered)})" if answered is not None else ""
            head = " ".join(str(p) for p in (message.get("status"), message.get("title")) if p)
            self.console.print(f"error{about}: {head}: {message.get('detail', '')}", style="red", markup=False)

    def close_stack(self, message: dict[str, Any]) -> None:
        """Print the stack's table with its final poses and the line on its acceptance and coverage."""
        name = message.get("stack")
        final = message.get("slices") or []
        for s in final:
            self.rows.setdefault((name, s.get("index")), {"stack": name}).update(
                {k: v for k, v in s.items() if k != "latency_ms"})
        self.finished.add(name)
        rows = [row for (stack, _), row in self.rows.items() if stack == name]
        self.console.print(self.table(sorted(rows, key=lambda r: r.get("index", 0)),
                                      f"stack {name}: final poses"))
        accepted = sum(1 for s in final if s.get("accepted"))
        self.console.print(f"stack {name}: {accepted}/{len(final)} accepted · "
                           f"reacquire: {reacquire_text(message.get('reacquire'))} · "
                           f"coverage {coverage_text(message.get('coverage'))}", markup=False)

    def table(self, rows: list[dict[str, Any]], title: str | None = None) -> Table:
        table = Table(title=title, title_justify="left")
        for col, just in (("stack", "left"), ("index", "right"), ("accepted", "left"),
                          ("expected error", "right"), ("translation (mm)", "right"), ("latency", "right"),
                          ("updated", "left")):
            table.add_column(col, justify=just)  # type: ignore[arg-type]
        for row in rows:
            table.add_row(*pose_cells(row))
        return table

    def renderable(self) -> Table:
        """The open stack's slices, the latest that fit the terminal."""
        rows = [row for (stack, _), row in self.rows.items() if stack not in self.finished]
        room = max(self.console.height - 8, 3)
        return self.table(rows[-room:], f"streaming ({len(rows)} slices, the last {min(len(rows), room)} shown)"
                          if len(rows) > room else "streaming")


def sent_label(sent: Sent) -> str:
    """How a message of the client is named to the user.

    Example:
        >>> from client.stream import Sent
        >>> sent_label(Sent("slice", "ax", 3)), sent_label(Sent("end_stack", "ax"))
        ('slice ax #3', 'end_stack ax')
    """
    return " ".join(p for p in (sent.type, sent.stack, None if sent.index is None else f"#{sent.index}") if p)


def pose_cells(row: dict[str, Any]) -> list[str]:
    """A pose's cells in ``svrnet stream``'s table.

    Example:
        >>> pose_cells({"stack": "ax", "index": 3, "accepted": False, "reason": "high_expected_error",
        ...             "expected_error_mm": 7.25, "translation_mm": [1, -2.5, 30], "latency_ms": 21.4})
        ['ax', '3', '✗ high_expected_error', '7.2 mm', '(1.0, -2.5, 30.0)', '21 ms', '']
    """
    expected, translation, latency = row.get("expected_error_mm"), row.get("translation_mm"), row.get("latency_ms")
    return [str(row.get("stack", "")), str(row.get("index", "")),
            "✓" if row.get("accepted") else f"✗ {row.get('reason') or ''}".rstrip(),
            "-" if expected is None else f"{expected:.1f} mm",
            "-" if not translation else "(" + ", ".join(f"{v:.1f}" for v in translation) + ")",
            "-" if latency is None else f"{latency:.0f} ms", "updated" if row.get("updated") else ""]


def reacquire_text(reacquire: list[dict[str, Any]] | None) -> str:
    """The slices worth acquiring again, by reason.

    Example:
        >>> reacquire_text([{"index": 3, "reason": "high_expected_error"}, {"index": 7, "reason": "empty"},
        ...                 {"index": 4, "reason": "high_expected_error"}])
        'high_expected_error #3 #4; empty #7'
        >>> reacquire_text([])
        'none'
    """
    by_reason: dict[str, list[str]] = {}
    for r in reacquire or []:
        by_reason.setdefault(str(r.get("reason")), []).append(f"#{r.get('index')}")
    return "; ".join(f"{reason} {' '.join(indices)}" for reason, indices in by_reason.items()) or "none"


def coverage_text(coverage: dict[str, Any] | None) -> str:
    """The coverage of the atlas brain in words.

    Example:
        >>> coverage_text({"brain_fraction": 0.834, "gaps": [{"extent_mm": 12.0}]})
        '83% of the brain, 1 gap'
    """
    coverage = coverage or {}
    fraction, gaps = coverage.get("brain_fraction"), len(coverage.get("gaps") or [])
    return f"{'-' if fraction is None else f'{fraction:.0%}'} of the brain, {gaps} gap{'' if gaps == 1 else 's'}"


@app.command(epilog=EXIT_HELP)
def stream(
    stacks: Annotated[list[Path], typer.Argument(exists=True, dir_okay=False, readable=True,
                                                 help=".nii or .nii.gz stacks, sent one after the other")],
    mask: MaskOpt = None,
    server: ServerOpt = DEFAULT_SERVER,
    api_key: Annotated[Optional[str], typer.Option(envvar="SVRNET_API_KEY", show_default=False,
                                                   help="API key (default $SVRNET_API_KEY)")] = None,
    pace: Annotated[float, typer.Option(
        min=0, help="seconds between two slices (0: as fast as the answers come)")] = 0.0,
    order: Annotated[SendOrder, typer.Option(help="acquisition order: sequential, or interleaved (even "
                                                  "indices, then odd)")] = SendOrder.sequential,
    mc_samples: McSamplesOpt = None,
    threshold: ThresholdOpt = None,
    max_expected_error: MaxExpectedOpt = None,
    bias_correction: BiasCorrectionOpt = True,
    model: ModelOpt = None,
    json_out: Annotated[Optional[Path], typer.Option(
        "--json-out", dir_okay=False, help="write every message received here, one JSON object a line")] = None,
) -> None:
    """Send stacks slice by slice as a scanner would (WebSocket /v1/stream) and show each pose as it comes."""
    from client import stream as streaming

    _check_masks(stacks, mask)
    _check_writable(json_out)
    console = _stdout()
    view = StreamView(console)
    with _errors():
        read = [streaming.read_stack(path, m) for path, m in zip(stacks, mask or [None] * len(stacks))]
        names = Counter(st.name for st in read)
        read = [streaming.ScannerStack(f"{st.name}#{i}" if names[st.name] > 1 else st.name, st.slice_axis, st.slices)
                for i, st in enumerate(read)]
        with Live(view.renderable(), console=console, auto_refresh=False, transient=True) as live:
            def on_message(message: dict[str, Any], answered: Sent | None) -> None:
                view.on_message(message, answered)
                live.update(view.renderable(), refresh=True)

            result = streaming.stream_stacks(
                read, server, api_key=api_key or None, mc_samples=mc_samples, variance_threshold=threshold,
                max_expected_error_mm=max_expected_error, bias_correction=None if bias_correction else False,
                model=model, pace_s=pace, order=order.value, on_message=on_message, json_out=json_out,
                answer_timeout_s=_timeout().read or 300.0)
        summary = result.summary or {}
        timing = summary.get("timing_ms") or {}
        p50, p95 = timing.get("pose_latency_p50"), timing.get("pose_latency_p95")
        console.print(f"session: {len(summary.get('stacks') or [])} stack(s), {summary.get('slices', 0)} slices · "
                      f"pose latency p50 {'-' if p50 is None else f'{p50:.0f}'} ms, "
                      f"p95 {'-' if p95 is None else f'{p95:.0f}'} ms · "
                      f"coverage {coverage_text(summary.get('coverage'))}", markup=False)
        errors = len(result.of_type("error"))
        if errors:
            console.print(f"{errors} error(s) from the server (above, in red)", style="red")
        if json_out is not None:
            console.print(f"wrote {json_out}")


@app.command(epilog=EXIT_HELP)
def status(
    job: Annotated[str, typer.Argument(help="job id")],
    server: ServerOpt = DEFAULT_SERVER,
    as_json: Annotated[bool, typer.Option("--json", help="print the raw JSON")] = False,
) -> None:
    """Status of a reconstruction job (GET /v1/reconstructions/{job})."""
    job = _job_id(job)
    with _errors(), _client(server) as svr:
        state = svr.status(job)
        console = _stdout()
        if as_json:
            console.print_json(data=state)
            return
        table = Table(show_header=False, title=f"job {job}", title_justify="left")
        table.add_column("field", style="bold")
        table.add_column("value")
        for key in ("status", "stage", "progress", "error", "created_at", "updated_at", "result_url",
                    "preview_url"):
            value = state.get(key)
            if key == "progress" and isinstance(value, (int, float)):
                value = f"{value:.0%}"
            table.add_row(key, "-" if value is None else str(value))
        console.print(table)


@app.command(epilog=EXIT_HELP)
def cancel(
    job: Annotated[str, typer.Argument(help="job id")],
    server: ServerOpt = DEFAULT_SERVER,
) -> None:
    """Cancel a queued or running job and delete its files (DELETE /v1/reconstructions/{job})."""
    job = _job_id(job)
    with _errors(), _client(server) as svr:
        svr.cancel(job)
        _stdout().print(f"job {job} cancelled")


@app.command(epilog=EXIT_HELP)
def models(
    server: ServerOpt = DEFAULT_SERVER,
    as_json: Annotated[bool, typer.Option("--json", help="print the raw JSON")] = False,
) -> None:
    """Models the server offers (GET /v1/models)."""
    with _errors(), _client(server) as svr:
        listed = svr.models()
        console = _stdout()
        if as_json:
            console.print_json(data=listed)
            return
        table = Table()
        for col in ("name", "version", "backbone", "label_type", "input_size", "spacing_mm", "variance_threshold",
                    "trained_on", "sha256"):
            table.add_column(col)
        for m in listed:
            row = [m.get(c) for c in ("name", "version", "backbone", "label_type", "input_size", "spacing_mm",
                                      "variance_threshold", "trained_on")]
            table.add_row(*("-" if v is None else str(v) for v in row), str(m.get("sha256", ""))[:12])
        console.print(table)


if __name__ == "__main__":  # pragma: no cover
    app()
