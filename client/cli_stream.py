"""``svrnet stream``: stacks sent slice by slice as a scanner sends them, each pose shown as it comes.

The command streams over ``/v1/stream`` (:mod:`client.stream`, which needs numpy and nibabel and is
imported when the command runs), draws the poses in a live table (:class:`~client.stream_views.StreamView`)
and ends with the session's summary, the slices worth acquiring again and the exit code of what
the stacks' final answers hold.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Optional

import typer
from rich.live import Live

from client._client import DEFAULT_SERVER
from client.cli_support import (ApiKeyOpt, BiasCorrectionOpt, MaskOpt, MasksHoldCsfOpt, MaxExpectedOpt, McSamplesOpt,
                                ModelOpt, OverwriteOpt, ServerOpt, ThresholdOpt, check_masks, check_writable,
                                timeout_from_env, user_path)
from client.errors import SVRnetError
from client.exits import EXIT_BAD_INPUT, EXIT_NOTHING_USABLE, errors, stdout
from client.stream_views import StreamView, coverage_text, reacquire_text
from client.views import usable

if TYPE_CHECKING:                     # client.stream needs numpy and nibabel: imported by `svrnet stream` only
    from client.stream import Sent


def stream(
    stacks: Annotated[list[Path], typer.Argument(exists=True, dir_okay=False, readable=True,
                                                 help=".nii or .nii.gz stacks, sent one after the other")],
    mask: MaskOpt = None,
    server: ServerOpt = DEFAULT_SERVER,
    api_key: ApiKeyOpt = None,
    pace: Annotated[float, typer.Option(
        min=0, help="seconds between two slices (0: as fast as the answers come)")] = 0.0,
    order: Annotated[Optional[list[str]], typer.Option(
        "--slice-order", "--order",
        help="acquisition order the slices are sent in, once for every stack or once per stack: sequential "
             "(the default), interleaved (even indices first), interleaved-even-first, interleaved-odd-first, "
             "or slice indices as acquired (0,2,4,1,3)")] = None,
    mc_samples: McSamplesOpt = None,
    threshold: ThresholdOpt = None,
    max_expected_error: MaxExpectedOpt = None,
    bias_correction: BiasCorrectionOpt = True,
    masks_hold_csf: MasksHoldCsfOpt = False,
    model: ModelOpt = None,
    json_out: Annotated[Optional[Path], typer.Option(
        "--json-out", dir_okay=False, callback=user_path,
        help="write every message received here, one JSON object a line")] = None,
    overwrite: OverwriteOpt = False,
) -> None:
    """Send stacks slice by slice as a scanner would (WebSocket /v1/stream) and show each pose as it comes."""
    from client import stream as streaming

    check_masks(stacks, mask, masks_hold_csf)
    check_writable(overwrite, json_out=json_out)
    console = stdout()
    view = StreamView(console)
    with errors():
        read = [streaming.read_stack(path, m) for path, m in zip(stacks, mask or [None] * len(stacks))]
        names = Counter(st.name for st in read)
        read = [streaming.ScannerStack(f"{st.name}#{i}" if names[st.name] > 1 else st.name, st.slice_axis, st.slices)
                for i, st in enumerate(read)]
        try:
            with Live(view.renderable(), console=console, auto_refresh=False, transient=True) as live:
                def on_message(message: dict[str, Any], answered: Sent | None) -> None:
                    view.on_message(message, answered)
                    live.update(view.renderable(), refresh=True)

                result = streaming.stream_stacks(
                    read, server, api_key=api_key or None, mc_samples=mc_samples, variance_threshold=threshold,
                    max_expected_error_mm=max_expected_error, bias_correction=None if bias_correction else False,
                    masks_hold_csf=True if masks_hold_csf else None, model=model, pace_s=pace,
                    order=order or "sequential", on_message=on_message, json_out=json_out,
                    answer_timeout_s=timeout_from_env().read or 300.0)
        except SVRnetError:
            view.print_open()                          # the transient table goes with the session: keep its rows
            raise
        summary = result.summary or {}
        timing = summary.get("timing_ms") or {}
        p50, p95 = timing.get("pose_latency_p50"), timing.get("pose_latency_p95")
        console.print(f"session: {len(summary.get('stacks') or [])} stack(s), {summary.get('slices', 0)} slices · "
                      f"pose latency p50 {'-' if p50 is None else f'{p50:.0f}'} ms, "
                      f"p95 {'-' if p95 is None else f'{p95:.0f}'} ms · "
                      f"coverage {coverage_text(summary.get('coverage'))}", markup=False)
        for name, slices in (summary.get("reacquire") or {}).items():
            if slices:
                console.print(f"worth acquiring again, stack {name}: {reacquire_text(slices)}", markup=False)
        for name, left in (summary.get("unfinished") or {}).items():
            missing = left.get("missing") or []
            console.print(f"stack {name}: no final poses" + (f", slices {', '.join(map(str, missing))} never arrived"
                                                            if missing else " (never ended)"), style="red")
        error_count = len(result.of_type("error"))
        if error_count:
            console.print(f"{error_count} error(s) from the server (above, in red)", style="red")
        for name, left in result.unsent.items():
            console.print(f"stack {name}: slices {', '.join(map(str, left))} not posed: the "
                          "server's session was full; stream them in another session", style="red", markup=False)
        if json_out is not None:
            console.print(f"wrote {json_out}")
    if result.unsent or (result.summary or {}).get("unfinished"):
        raise typer.Exit(EXIT_BAD_INPUT)                   # what the session could not take, or end, is not posed
    if error_count and not result.of_type("pose"):
        raise typer.Exit(EXIT_BAD_INPUT)                   # the server refused every slice
    if not usable({"stacks": result.of_type("stack")}):
        raise typer.Exit(EXIT_NOTHING_USABLE)              # no slice accepted in the stacks' final answers
