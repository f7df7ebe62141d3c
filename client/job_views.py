"""What ``svrnet`` shows of a reconstruction job: its progress bar's label, its status table and the
report's lines (quality, refined poses), each built from the API's JSON bodies alone.

Example:
    >>> stage_label({"status": "queued", "stage": "queued", "workers": 0})
    'queued: no worker is running (svrnet-worker)'
"""

from __future__ import annotations

from typing import Any

from rich.table import Table

NO_WORKER = "no worker is running (svrnet-worker)"
"""What a queued job waits for when the server says no worker serves its queue."""


def waits_for_a_worker(state: dict[str, Any]) -> bool:
    """Whether a job's status says it is queued and no worker serves its queue.

    Example:
        >>> waits_for_a_worker({"status": "queued", "workers": 0}), waits_for_a_worker({"status": "queued"})
        (True, False)
    """
    return state.get("status") == "queued" and state.get("workers") == 0


def stage_label(state: dict[str, Any]) -> str:
    """The progress bar's label: the job's status and the stage it is in.

    Example:
        >>> stage_label({"status": "running", "stage": "stack registration"})
        'running: stack registration'
        >>> stage_label({"status": "queued", "stage": "queued"})
        'queued'
        >>> stage_label({"status": "queued", "stage": "queued", "workers": 0})
        'queued: no worker is running (svrnet-worker)'
    """
    status, stage = state.get("status"), state.get("stage")
    if waits_for_a_worker(state):
        return f"queued: {NO_WORKER}"
    return str(status) if not stage or stage == status else f"{status}: {stage}"


def quality_line(quality: dict[str, Any] | None, stacks: int | None = None) -> str:
    """The job report's ``quality`` in one line (empty when the job has none); ``stacks``: how many the
    job had (with one, no stack can be left out, and the line says so).

    Example:
        >>> quality_line({"judged_slices": 80, "leave_one_stack_out": {"median_ncc": 0.8,
        ...               "per_stack_median_ncc": [0.8, None]}}).split("; ")[1]
        'leave one stack out 0.80 (per stack 0.80, - (not in the volume))'
        >>> quality_line({"judged_slices": 80, "median_ncc": 0.91, "fraction_ncc_above_0_7": 0.95,
        ...               "leave_one_stack_out": {"median_ncc": 0.84, "per_stack_median_ncc": [0.86, 0.8, 0.85]}})
        'quality: slices vs volume median NCC 0.91, 95% above 0.7 (80 slices); leave one stack out 0.84 (per stack 0.86, 0.80, 0.85)'
        >>> quality_line({"judged_slices": 80, "path": "slice_level", "paths": {"full": 0.8, "slice_level": 0.85},
        ...               "further_passes": {"scores": [0.85, 0.86], "kept": 1}}, stacks=3).split("; ")[-1]
        'slices registered one by one + 1 further slice-level pass'
        >>> quality_line({"judged_slices": 8, "path": "full", "paths": {"full": None}}).split("; ")[-1]   # nothing compared
        'path full'
        >>> quality_line({"judged_slices": 22, "median_ncc": 0.99, "fraction_ncc_above_0_7": 1.0}, stacks=1).split("; ")[1]
        'leave one stack out: - (one stack: the volume is judged by its own slices only)'
        >>> quality_line({"judged_slices": 22, "median_ncc": 0.99, "fraction_ncc_above_0_7": 1.0,
        ...               "leave_alternate_slices_out": {"median_ncc": 0.12, "even_odd_median_ncc": [0.1, 0.14]}},
        ...              stacks=1).split("; ")[1]
        'one stack: leave alternate slices out 0.12 (even 0.10, odd 0.14)'
    """
    if not quality:
        return ""
    held = quality.get("leave_one_stack_out") or {}
    num = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
    share = quality.get("fraction_ncc_above_0_7")
    line = (f"quality: slices vs volume median NCC {num(quality.get('median_ncc'))}, "
            f"{'-' if share is None else f'{share:.0%}'} above 0.7 ({quality.get('judged_slices', 0)} slices)")
    alternate = quality.get("leave_alternate_slices_out") or {}
    if held.get("median_ncc") is not None:
        per = ", ".join("- (not in the volume)" if x is None else num(x) for x in held.get("per_stack_median_ncc") or [])
        line += f"; leave one stack out {num(held['median_ncc'])} (per stack {per})"
    elif alternate.get("median_ncc") is not None:      # a lone stack's slices agree with any volume of themselves
        even, odd = (alternate.get("even_odd_median_ncc") or [None, None])[:2]
        line += f"; one stack: leave alternate slices out {num(alternate['median_ncc'])} (even {num(even)}, odd {num(odd)})"
    else:
        line += "; leave one stack out: -" + (" (one stack: the volume is judged by its own slices only)"
                                              if stacks == 1 else "")
    if quality.get("path"):
        kept = (quality.get("further_passes") or {}).get("kept") or 0
        compared = len(quality.get("paths") or {}) > 1           # one path alone (no registration asked): its key
        words = PATH_WORDS.get(quality["path"]) if compared else None
        line += f"; {words}" if words else f"; path {quality['path']}"
        if kept:
            line += f" + {kept} further slice-level pass{'es' if kept > 1 else ''}"
    return line


PATH_WORDS = {"full": "slices registered (stacks, then slices)", "slice_level": "slices registered one by one",
              "starting_poses": "slices kept at their starting poses (registration did not make them agree better)"}
"""How the quality line names the job's path (``quality.path``: docs/reconstruction.md)."""


def refined_poses_line(summary: dict[str, Any] | None) -> str:
    """The job report's ``refined_poses`` in one line (empty when the report has none, or no posed
    slice: poses uploaded without expected errors): how many of the posed slices the job placed and
    how, and their median expected error against the starting poses'.

    Example:
        >>> print(refined_poses_line({"posed": 4, "in_volume": 2, "placed_by_stack_motion": 1, "placed_by_volume": 0,
        ...                           "median_expected_error_mm": 2.5, "median_starting_expected_error_mm": 6.5}))
        refined poses: 3 of 4 posed slices placed (2 in the volume, 1 by their stack's motion, 0 registered to it); median expected error 2.50 mm (starting poses 6.50 mm)
        >>> refined_poses_line({"posed": 0, "in_volume": 0})
        ''
    """
    if not summary or not summary.get("posed"):
        return ""
    inside, motion, volume = (int(summary.get(k) or 0) for k in ("in_volume", "placed_by_stack_motion",
                                                                  "placed_by_volume"))
    line = (f"refined poses: {inside + motion + volume} of {summary.get('posed', 0)} posed slices placed "
            f"({inside} in the volume, {motion} by their stack's motion, {volume} registered to it)")
    if summary.get("median_expected_error_mm") is not None:
        line += f"; median expected error {summary['median_expected_error_mm']:.2f} mm"
        if summary.get("median_starting_expected_error_mm") is not None:
            line += f" (starting poses {summary['median_starting_expected_error_mm']:.2f} mm)"
    return line


def job_table(state: dict[str, Any], job: str) -> Table:
    """The table of ``svrnet status``: a reconstruction job's fields, one a row."""
    table = Table(show_header=False, title=f"job {job}", title_justify="left")
    table.add_column("field", style="bold")
    table.add_column("value", overflow="fold")            # a URL whole on any terminal, not cut at its width
    for key in ("status", "stage", "progress", "error", "created_at", "updated_at", "result_url",
                "preview_url"):
        value = state.get(key)
        if key == "progress" and isinstance(value, (int, float)):
            value = f"{value:.0%}"
        table.add_row(key, "-" if value is None else str(value))
    if state.get("status") == "queued" and state.get("workers") is not None:
        table.add_row("workers", NO_WORKER if waits_for_a_worker(state) else str(state["workers"]))
    return table
