"""What the ``svrnet`` commands share: their options, the checks made before anything is sent, and
following a reconstruction job to its files (:mod:`client.cli` holds the commands).

Example:
    >>> positive(2.5)
    2.5
    >>> job_id_of("  3f2a ")
    '3f2a'
"""

from __future__ import annotations

import json
import os
import re
import time
from pathlib import Path
from typing import Annotated, Any, Optional

import httpx
import typer
from rich.progress import BarColumn, Progress, SpinnerColumn, TaskProgressColumn, TextColumn, TimeElapsedColumn

from client._client import SVRnetClient
from client.errors import Busy
from client.files import write_whole
from client.job_calls import UNREACHABLE_S
from client.exits import EXIT_NOT_FOUND, EXIT_USAGE, fail, stderr, stdout
from client.job_views import NO_WORKER, quality_line, refined_poses_line, stage_label, waits_for_a_worker


def timeout_from_env() -> httpx.Timeout:
    """Read/write timeout from ``$SVRNET_TIMEOUT`` (seconds; default 300): a large request on a CPU
    server can take longer."""
    raw = os.environ.get("SVRNET_TIMEOUT", "300")
    try:
        seconds = float(raw)
    except ValueError:
        seconds = -1.0
    if not 0 < seconds < float("inf"):
        raise typer.BadParameter(f"SVRNET_TIMEOUT={raw!r}: must be a finite number of seconds > 0")
    return httpx.Timeout(connect=5.0, read=seconds, write=seconds, pool=5.0)


DEFAULT_VOLUME = Path("recon.nii.gz")
"""Where a job's volume is written without ``--out``."""


OverwriteOpt = Annotated[bool, typer.Option(
    "--overwrite", help="replace output files that exist (without it an existing one stops the command before "
                        "anything is sent)")]


def user_path(value: Path | None) -> Path | None:
    """An output path option as the user means it: ``~`` expanded when the option is parsed, so that
    the check before the upload and the write after it see one path (a shell leaves ``--out=~/x``, and
    a pipeline's argument list every ``~``, to the program).

    Example:
        >>> user_path(Path("~/p.json")) == Path.home() / "p.json", user_path(None)
        (True, None)
    """
    return None if value is None else value.expanduser()


def volume_path(value: Path | None) -> Path | None:
    """A volume file option (:func:`user_path`) whose name says NIfTI, as the volume is written:
    ``.nii.gz`` as the server sends it, ``.nii`` uncompressed; another name is refused before
    anything is sent (a file named ``.nrrd`` holding gzipped NIfTI opens nowhere).

    Example:
        >>> volume_path(Path("recon.NII")), volume_path(None)
        (PosixPath('recon.NII'), None)
        >>> try:
        ...     volume_path(Path("recon.mha"))
        ... except typer.BadParameter as e:
        ...     print(e)
        recon.mha: the volume is NIfTI; name it .nii.gz, or .nii to have it uncompressed
    """
    if value is not None and not value.name.lower().endswith((".nii.gz", ".nii")):
        raise typer.BadParameter(f"{value.name}: the volume is NIfTI; name it .nii.gz, or .nii to have it uncompressed")
    return user_path(value)


def check_writable(overwrite: bool = False, **paths: Path | None) -> None:
    """Output files (by option name) must be writable BEFORE anything is uploaded (not after an hour of
    reconstruction), and new unless ``overwrite``: a second patient's results never replace the first's
    under a default name; and distinct: one file named for two outputs would hold only the last."""
    taken: dict[Path, str] = {}
    for option, path in paths.items():
        if path is None:
            continue
        where, hint = path.expanduser().resolve(), f"--{option.replace('_', '-')}"
        other = taken.setdefault(where, option)
        if other != option:
            raise typer.BadParameter(f"{path} is also given to --{other.replace('_', '-')}; name each output its own "
                                     "file", param_hint=hint)
        if not overwrite and where.is_file():
            raise typer.BadParameter(f"{path} exists; nothing was sent (--overwrite replaces it)", param_hint=hint)
        if not where.parent.is_dir() or not os.access(where.parent, os.W_OK):
            raise typer.BadParameter(f"{path}: its folder {where.parent} does not exist or is not writable",
                                     param_hint=hint)
        if where.is_dir():
            raise typer.BadParameter(f"{path} is a folder, not a file", param_hint=hint)


def check_folder_writable(option: str, folder: Path) -> None:
    """An output folder (by option name) must be, or be made now as, a writable folder BEFORE anything
    is uploaded: no file in its place, and its nearest existing folder writable."""
    folder = folder.expanduser().resolve()
    existing = next(p for p in (folder, *folder.parents) if p.exists())
    if not existing.is_dir() or not os.access(existing, os.W_OK):
        raise typer.BadParameter(f"{folder}: {existing} is not a writable folder",
                                 param_hint=f"--{option.replace('_', '-')}")
    try:                       # made now: permissions are not the whole story (root in /proc, a read-only mount)
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise typer.BadParameter(f"{folder} cannot be made ({e.strerror or e})",
                                 param_hint=f"--{option.replace('_', '-')}") from None


def job_id_of(job: str) -> str:
    """The job id as given, without surrounding blanks (an empty one is a usage error)."""
    if not job.strip():
        raise typer.BadParameter("the job id is empty", param_hint="JOB")
    return job.strip()


def check_masks(stacks: list[Path], masks: list[Path] | None, masks_hold_csf: bool = False) -> None:
    """None, or one mask per stack (a usage error otherwise); ``--masks-hold-csf`` without masks is
    said to do nothing (it tells how the uploaded masks were drawn)."""
    if masks and len(masks) != len(stacks):
        raise typer.BadParameter(f"{len(masks)} masks for {len(stacks)} stacks; give none or one per stack",
                                 param_hint="--mask")
    if masks_hold_csf and not masks:
        stderr().print("--masks-hold-csf: no --mask given, so it does nothing (the service's own masks are "
                       "made as the pose network needs them)", markup=False)


def positive(value: float | None) -> float | None:
    """An option's value when it is > 0 (or not given); a usage error otherwise."""
    if value is not None and not value > 0:
        raise typer.BadParameter("must be > 0")
    return value


ORDER_WORDS = ("auto", "sequential", "interleaved", "interleaved-even-first", "interleaved-odd-first")
"""The acquisition orders ``/v1/predict`` and a job take by name (``auto``: the server's motion model chooses)."""
SLICE_INDICES = re.compile(r"\d{1,6}( *, *\d{1,6})*")


def slice_order_words(values: list[str] | None) -> list[str] | None:
    """``--slice-order`` values that the server can take: a name of :data:`ORDER_WORDS` or slice
    indices as acquired; a usage error naming the value otherwise, before anything is sent (the server
    checks that indices list each of the stack's slices once).

    Example:
        >>> slice_order_words(["interleaved", " 0,2,1 "])
        ['interleaved', ' 0,2,1 ']
    """
    for value in values or []:
        text = value.strip()
        if text not in ORDER_WORDS and not SLICE_INDICES.fullmatch(text):
            raise typer.BadParameter(f"{value!r} is none of {', '.join(ORDER_WORDS)}, nor slice indices as acquired "
                                     "(0,2,4,1,3)")
    return values


def resolution_range(value: float | None) -> float | None:
    """``--resolution`` within what the server takes (0.2 < mm <= 5), else a usage error naming it.

    Example:
        >>> resolution_range(0.8), resolution_range(None)
        (0.8, None)
    """
    if value is not None and not 0.2 < value <= 5.0:
        raise typer.BadParameter("must be over 0.2 and at most 5 (mm)")
    return value


def once_or_per_stack(values: list | None, stacks: list, option: str) -> None:
    """A usage error naming ``option`` where it is given neither once nor once per stack."""
    if values and len(values) not in (1, len(stacks)):
        fail(f"{option}: {len(values)} values for {len(stacks)} stacks; give one for every stack or one per stack",
             EXIT_USAGE)


def write_json(path: Path, body: Any) -> None:
    """``body`` as indented JSON in ``path``, whole or not at all (a full disk leaves the file it
    would have replaced as it was)."""
    write_whole(path, (json.dumps(body, indent=2) + "\n").encode())


MaxExpectedOpt = Annotated[Optional[float], typer.Option(
    "--max-expected-error", callback=positive,
    help="accept only slices whose expected error (mm) is at most this (default: the model's)")]
ServerOpt = Annotated[str, typer.Option("--server", envvar="SVRNET_SERVER", help="server URL")]
ApiKeyOpt = Annotated[Optional[str], typer.Option("--api-key", envvar="SVRNET_API_KEY", show_default=False,
                                                  help="API key, where the server asks for one")]
MasksHoldCsfOpt = Annotated[bool, typer.Option(
    "--masks-hold-csf", help="the masks are the skull's inside (brain and the CSF around it, as manual fetal masks "
                             "are usually drawn): the pose network sees them less their outer 2 mm")]
STACK_SPACE_HELP = ("write the volume in the scanner coordinates of the job's stack N (0: its first stack), where the "
                    "brain was while that stack was acquired, so that it overlays the stack in a viewer (default: atlas "
                    "space)")
StackSpaceOpt = Annotated[Optional[int], typer.Option("--stack-space", min=0, help=STACK_SPACE_HELP)]
DELETE_HELP = ("delete the job and its results on the server once every file asked for is written (without it the "
               "server keeps them until the time printed, SVRNET_RETENTION_HOURS after the job ended)")
DeleteOpt = Annotated[bool, typer.Option("--delete", help=DELETE_HELP)]
McSamplesOpt = Annotated[Optional[int], typer.Option(min=1, max=1000, help="MC-dropout passes per slice "
                                                                           "(default: the server's, 100)")]
ThresholdOpt = Annotated[Optional[float], typer.Option(
    "--threshold", callback=positive,
    help="geodesic-variance threshold (about mm^2: the MC samples' mean squared distance from their mean, "
    "translations in mm plus twice the rotations in rad^2) (default: the model's; see `svrnet models`); a loose "
    "guard: --max-expected-error is the one to set")]
BiasCorrectionOpt = Annotated[bool, typer.Option("--bias-correction/--no-bias-correction",
                                                 help="N4 bias-field correction")]
ModelOpt = Annotated[Optional[str], typer.Option(help="model name (see `svrnet models`)")]
MaskOpt = Annotated[Optional[list[Path]], typer.Option(
    "--mask", "-m", exists=True, dir_okay=False, readable=True, metavar="MASK",
    help="brain mask (drawn to the skull's inside, as fetal masks usually are: add --masks-hold-csf; a box around "
         "the head is searched for the brain); repeat, one per stack in the same order (or none)")]
JobArg = Annotated[str, typer.Argument(help="job id (as `svrnet reconstruct` printed it)")]
StacksArg = Annotated[list[Path], typer.Argument(
    exists=True, readable=True, metavar="STACK",
    help=".nii, .nii.gz, .nrrd, .mha, .dcm, or a DICOM series as a .zip or a folder (sent zipped)")]



COHERENT_NCC = 0.5
"""The held-out median NCC under which the service calls a volume (or one stack of it) no coherent
brain (``service.reconstruction.quality.MIN_HELD_OUT_NCC``; the client does not import the service)."""
UNSETTLED_MM = 10.0
"""A job whose refined poses' median expected error exceeds this has many slices whose left-right
branch is not settled (extreme motion: 23 mm where 34 % of the slices sat on their mirror twin,
against about 2 mm for jobs of mild to independent motion); the leave-one-stack-out score cannot
see a volume so blended, for a slice and its twin look alike."""


def follow_job(svr: SVRnetClient, job_id: str, poll: float, timeout: float) -> dict[str, Any]:
    """Wait for a job, with a progress bar on a terminal, else a line on stderr at each change of
    stage (a script's log shows where the job is); its final status body."""
    err = stderr()
    with Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), TaskProgressColumn(),
                  TimeElapsedColumn(), console=err, transient=True, disable=not err.is_terminal) as bar:
        task = bar.add_task("queued", total=1.0)
        told, last = False, None
        started = time.monotonic()

        def on_progress(state: dict[str, Any]) -> None:
            nonlocal told, last
            label = stage_label(state)
            bar.update(task, completed=float(state.get("progress") or 0.0), description=label)
            if waits_for_a_worker(state) and not told:
                told, last = True, label               # once, also where no bar is drawn (a pipe, a log)
                bar.console.print(f"job {job_id} is queued and {NO_WORKER}: it starts once svrnet-worker runs "
                                  "with the server's SVRNET_QUEUE_URL and data folder", style="yellow", markup=False)
            elif not err.is_terminal and label != last:
                last = label
                err.print(f"job {job_id}: {label} ({time.monotonic() - started:.0f} s)", markup=False, highlight=False)

        def on_unreachable(exc: Exception | None) -> None:
            if exc is None:
                bar.console.print(f"job {job_id}: the server answers again", markup=False, highlight=False)
                return
            why = " ".join(str(exc).split())
            state = "is busy" if isinstance(exc, Busy) else "does not answer"
            bar.console.print(f"job {job_id}: the server {state} ({why}); trying again for up to "
                              f"{UNREACHABLE_S:.0f} s (the job goes on on the server)", style="yellow", markup=False)

        return svr.wait(job_id, poll_s=poll, timeout_s=timeout, on_progress=on_progress, on_unreachable=on_unreachable)


def stack_frame_entry(done: dict[str, Any], stack: int) -> dict[str, Any]:
    """The finished job's ``report.stack_frames[stack]``; ends the command (exit 6, nothing downloaded)
    where the job has no place for that stack, or a server too old to place the volume by a stack.

    Example:
        >>> frames = [{"stack": 0, "scanner_from_atlas": [], "slices": 3}]
        >>> stack_frame_entry({"report": {"stack_frames": frames}}, 0)["slices"]
        3
    """
    frames = (done.get("report") or {}).get("stack_frames")
    if frames is None:
        fail("--stack-space: this server does not place volumes by a stack (its job reports have no "
             "stack_frames); fetch the atlas-space volume without --stack-space", EXIT_NOT_FOUND)
    if not 0 <= stack < len(frames):
        fail(f"--stack-space: the job's stacks are 0-{len(frames) - 1}", EXIT_NOT_FOUND)
    if frames[stack].get("scanner_from_atlas") is None:
        fail(f"--stack-space: stack {stack} has no slice in the volume, so no place to put the volume by; "
             "choose another stack", EXIT_NOT_FOUND)
    return frames[stack]


def write_results(svr: SVRnetClient, job_id: str, done: dict[str, Any], out: Path | None, preview: Path | None,
                  poses_out: Path | None, transforms_out: Path | None, stack_space: int | None = None) -> bool:
    """Download a succeeded job's volume (``out``, default ``recon.nii.gz``; with ``stack_space``, placed in
    that stack's scanner coordinates) and the files asked for, and print its quality; True when the
    volume is no coherent brain."""
    console = stdout()
    target = out if out is not None else DEFAULT_VOLUME
    frame = None
    if stack_space is not None:            # checked before any download: a server that ignores ?stack= would
        frame = stack_frame_entry(done, stack_space)   # send the atlas-space volume
    svr.download_volume(job_id, target, stack=stack_space)
    where = "" if frame is None else f" (the scanner coordinates of stack {stack_space})"
    console.print(f"job {job_id} succeeded; wrote {target}{where}")
    if frame is not None and frame.get("motion_mm") is not None:
        console.print(f"stack {stack_space}: placed by {frame['slices']} of its slices, which moved "
                      f"{frame['motion_mm']:.1f} mm (median) about that place", markup=False)
    report = done.get("report") or {}
    for line in (quality_line(report.get("quality"), report.get("n_stacks")), refined_poses_line(report.get("refined_poses"))):
        if line:
            console.print(line, markup=False)
    quality = report.get("quality") or {}
    incoherent = quality.get("coherent") is False
    if incoherent:
        what = (f"the stack's slices do not predict each other (leave alternate slices out under {COHERENT_NCC})"
                if quality.get("leave_alternate_slices_out") else
                f"the stacks do not predict each other (leave one stack out under {COHERENT_NCC})")
        console.print(f"{what}: the volume is no coherent brain; do not use it. Check the stacks' poses (svrnet "
                      "predict) and masks (svrnet masks)", style="bold red", markup=False)
    refined = (report.get("refined_poses") or {}).get("median_expected_error_mm")
    if refined is not None and refined > UNSETTLED_MM and not incoherent:
        console.print(f"the refined poses' median expected error is {refined:.0f} mm: many slices' left-right "
                      "branch is not settled, and the volume may blend the brain with its mirror image, which the "
                      "quality scores cannot see; judge it by the preview", style="yellow", markup=False)
    per_stack = (quality.get("leave_one_stack_out") or {}).get("per_stack_median_ncc") or []
    left_out = [int(i) for i in quality.get("stacks_left_out") or []]
    if left_out and not incoherent:
        console.print(f"stack {', '.join(map(str, left_out))}: the other stacks do not predict it (leave one stack "
                      f"out under {COHERENT_NCC}): another fetus, another contrast, or a stack far off; the volume "
                      "was made again without it, and its slices keep their starting expected errors. The others' "
                      "poses were predicted beside it: send the job again without it for the best volume",
                      style="yellow", markup=False)
    apart = [str(i) for i, x in enumerate(per_stack) if x is not None and x < COHERENT_NCC]
    if apart and not incoherent:
        console.print(f"stack {', '.join(apart)}: the other stacks do not predict it (leave one stack out under "
                      f"{COHERENT_NCC}): another fetus, another contrast, or a stack far off; its slices are in the "
                      "volume and keep their starting expected errors: send the job again without it",
                      style="yellow", markup=False)
    unused = [str(i) for i, x in enumerate(per_stack) if x is None and i not in left_out]
    if unused and len(per_stack) > 1 and not incoherent:
        console.print(f"stack {', '.join(unused)}: no slice of it is in the volume (none accepted, or no brain "
                      "found); the volume rests on the other stacks. See its slices in svrnet predict, or send "
                      "its mask", style="yellow", markup=False)
    if report.get("started_from") == "every_slice":
        console.print("started from every slice: too few were accepted to start from the accepted ones alone; "
                      "judge the volume by the quality line and the preview", style="yellow", markup=False)
    if preview is not None:
        svr.download_preview(job_id, preview)
        console.print(f"wrote {preview}")
    if poses_out is not None:
        write_json(poses_out, svr.refined_poses(job_id))
        console.print(f"wrote {poses_out}")
    if transforms_out is not None:
        svr.download_transforms(job_id, transforms_out)
        console.print(f"wrote {transforms_out}")
    return incoherent
