"""What ``svrnet`` shows: the tables and lines its commands print, built from the API's JSON bodies.

Nothing here talks to a server or reads a file: each table or line is built from a response body (a
dict), so the CLI's output is tested on bodies alone; :func:`upload_bar` is the progress bar an upload
feeds.

What ``svrnet stream`` shows lives in :mod:`client.stream_views`, what it shows of a reconstruction
job in :mod:`client.job_views`.

Example:
    >>> usable({"stacks": [{"slices": [{"reason": "empty"}, {"accepted": True}]}]})
    True
"""

from __future__ import annotations

import re
import statistics
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from rich import box
from rich.console import Console
from rich.progress import (BarColumn, DownloadColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn,
                           TransferSpeedColumn)
from rich.table import Table

NAME_WIDTH = 20
"""Stack file names up to this long stay on one line of the summary table; longer ones fold, so that
every column fits an 80-column terminal."""
SHORT_REASONS = {"empty": "empty", "degenerate_anchor_points": "degenerate", "outside_atlas": "outside",
                 "inconsistent_with_stack": "inconsistent", "high_expected_error": "error", "high_variance": "variance"}
"""The summary table's words for the answer's ``reason`` values (its caption names them), one a line,
so that no word is cut at 80 columns."""


def with_brain(slices: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The slices of a stack that hold brain: not ``empty`` (their pose says nothing), nor, in a
    stream's stack, ``not_received`` (never sent: no image to hold anything).

    Example:
        >>> [s["reason"] for s in with_brain([{"reason": None}, {"reason": "empty"}, {"reason": "not_received"}])]
        [None]
    """
    return [s for s in slices if s.get("reason") not in ("empty", "not_received")]


def usable(result: dict[str, Any]) -> bool:
    """Whether a ``/v1/predict`` body has an accepted slice (without one, ``svrnet predict`` ends with
    :data:`~client.exits.EXIT_NOTHING_USABLE`).

    Example:
        >>> usable({"stacks": [{"slices": [{"accepted": False}, {"accepted": True}]}]})
        True
    """
    return any(s.get("accepted") for st in result.get("stacks") or [] for s in st.get("slices") or [])


def summarise(result: dict[str, Any]) -> Table:
    """The per-stack summary table of a ``/v1/predict`` body."""
    model = result.get("model") or {}
    limit, threshold = result.get("max_expected_error_mm"), result.get("variance_threshold")
    title = (f"model {model.get('name', '?')} {model.get('version', '')} · mc_samples {result.get('mc_samples')} · "
             f"accepted: expected error <= {'-' if limit is None else f'{limit:.3g} mm'}, "
             f"variance <= {'-' if threshold is None else f'{threshold:.4g}'}")
    table = Table(title=title, title_justify="left", caption_justify="left", box=box.SIMPLE_HEAD, pad_edge=False,
                  collapse_padding=True,
                  caption="brain: the uploaded mask, or the intracranial volume the localiser found (brain and "
                          "the CSF around it; its confidence); "
                          "accepted: of the slices with brain (empty ones have none); rejected: every slice not "
                          "accepted, empty ones too, by reason: error = "
                          "high_expected_error, variance = high_variance, inconsistent = inconsistent_with_stack, "
                          "outside = outside_atlas, degenerate = degenerate_anchor_points; expected error (mm), "
                          "variance (the network's spread, about mm^2): their medians")
    stacks = result.get("stacks") or []
    longest = max([len(str(s.get("filename", ""))) for s in stacks] + [5])
    for col, just in (("stack", "left"), ("brain", "left"), ("accepted", "right"), ("rejected", "left"),
                      ("expected error", "right"), ("variance", "right")):
        # names up to NAME_WIDTH stay whole (the other columns wrap first), longer ones fold; no cell is cut short
        table.add_column(col, justify=just, overflow="fold", no_wrap=col == "stack" and longest <= NAME_WIDTH,  # type: ignore[arg-type]
                         min_width={"stack": min(longest, NAME_WIDTH), "rejected": 14}.get(col),
                         max_width=None if col in ("stack", "rejected") else 8)
    for stack in stacks:
        slices = stack.get("slices") or []
        accepted = sum(1 for s in slices if s.get("accepted"))
        reasons = Counter(s.get("reason") or "unknown" for s in slices if not s.get("accepted")).most_common()
        brain = with_brain(slices)
        variances = [s["geodesic_variance"] for s in brain if s.get("geodesic_variance") is not None]
        expected = [s["expected_error_mm"] for s in brain if s.get("expected_error_mm") is not None]
        where = stack.get("localisation") or {}
        found = "mask" if where.get("method") == "mask" else \
            f"{where.get('brain_volume_ml', 0):.0f} ml ({where.get('confidence', 0):.2f})" if where else "-"
        table.add_row(str(stack.get("filename", "")), found, f"{accepted} of {len(brain)}",
                      "\n".join(f"{SHORT_REASONS.get(k, k)} {v}" for k, v in sorted(reasons, key=lambda kv: (-kv[1], kv[0])))
                      or "-",
                      f"{statistics.median(expected):.1f} mm" if expected else "-",
                      f"{statistics.median(variances):.4g}" if variances else "-")
    return table


LOW_CONFIDENCE = 0.5
"""A localiser confidence under this gets a hint to look at the mask (docs/localisation.md gives the
confidences real stacks get)."""
LARGEST_BRAIN_ML = 700.0
"""An uploaded mask over this volume is no fetal brain mask (the service's localiser takes brains of
30-700 ml with their CSF as plausible; a term brain holds about 450)."""


def _mirrored(stack: dict[str, Any]) -> bool:
    """The request found the stack's voxels mirrored against its header (``consistency.mirrored``)."""
    return bool((stack.get("consistency") or {}).get("mirrored"))


def _apart_mm(stack: dict[str, Any]) -> float | None:
    """How far the stack's brain lies from the request's fetus where it is another's
    (``consistency.apart_from_request``, ``apart_mm``); None where it is not."""
    fit = stack.get("consistency") or {}
    return float(fit.get("apart_mm") or 0.0) if fit.get("apart_from_request") else None


def consistency_hints(name: str, stack: dict[str, Any]) -> list[str]:
    """What to do about a stack the request left out of its decisions: one whose voxels it found
    mirrored, or whose brain is another fetus's (``svrnet predict`` and ``svrnet stream`` say it alike).

    Example:
        >>> consistency_hints("ax.nii.gz", {"consistency": {"apart_from_request": True, "apart_mm": 96.4}})[0][:60]
        "ax.nii.gz: its brain lies 96 mm from the other stacks' (its "
    """
    hints = []
    if _mirrored(stack):
        hints.append(f"{name}: it lies on the mirror image of where the other stacks put the fetus, so none of its "
                     "slices is accepted: its file's voxels are most likely reversed or flipped against its header "
                     "(slices written in reverse order, rows or columns flipped, without the affine): convert the "
                     "series again from the scanner's files (e.g. dcm2niix); if it was, its own slices decided "
                     "its left-right branch wrongly: acquire it again")
    apart = _apart_mm(stack)
    if apart is not None:
        hints.append(f"{name}: its brain lies {apart:.0f} mm from the other stacks' (its mask holds another fetus's "
                     "brain, a twin's, or it is another scan's file), so none of its slices is accepted: send the "
                     "stacks of one fetus in a request, a twin's in a request of their own")
    return hints


MASK_NAME = re.compile(r"(^|[_\-.])mask([_\-.]|$)", re.IGNORECASE)
"""A file name that says it holds a mask (``axial_mask.nii.gz``, ``brain-mask.nii``; not ``unmasked``)."""


def predict_hints(result: dict[str, Any], stage_off: str | None = None) -> list[str]:
    """What to do about an answer with nothing usable in it: a stack without brain slices, a localiser
    that was unsure, no slice accepted (``stage_off``: the consistency stage the request turned off,
    which then comes first); and what to know of one that is usable: a stack noisier than the poses
    were calibrated on, slices whose brain lost its signal (one line each; none for a clean, usable
    answer).

    Example (one stack sent alone, nothing accepted):
        >>> body = {"max_expected_error_mm": 4.5, "stacks": [{"filename": "ax.nii.gz", "localisation": {
        ...     "method": "network", "confidence": 0.9}, "slices": [{"accepted": False, "reason": "high_expected_error"}]}]}
        >>> print(predict_hints(body)[0])
        no slice accepted (every one expects an error over 4.5 mm): a stack sent alone has no other stack to agree with; send all the stacks of a scan in one request (if nothing is accepted then either, the images are the cause: see the reasons above)
        >>> print(predict_hints(body, stage_off="the image consistency stage")[0][:70])
        fewer than half the slices accepted with the image consistency stage o
        >>> ok = {"slices": [{"accepted": True, "reason": None}] * 3}
        >>> print(predict_hints({"stacks": [ok, body["stacks"][0]]}, "the image consistency stage")[0][:61])
        ax.nii.gz: no slice accepted with the image consistency stage
    """
    hints = []
    stacks = result.get("stacks") or []
    for stack in stacks:
        name, where = stack.get("filename", "?"), stack.get("localisation") or {}
        brain = with_brain(stack.get("slices") or [])
        if not brain:
            hints.append(f"{name}: no slice with brain: " + (
                "its mask holds no brain on the stack's slices; check that it is the stack's mask"
                if where.get("method") == "mask" else
                "the localiser found none" + (
                    " and its name says mask: a mask sent as a stack? Pass each mask with --mask, after the stacks"
                    if MASK_NAME.search(name) else "; upload a brain mask with --mask")))
        elif where.get("method") == "mask" and float(where.get("brain_volume_ml") or 0.0) > LARGEST_BRAIN_ML:
            hints.append(f"{name}: its mask holds {float(where['brain_volume_ml']):.0f} ml, more than any fetal brain "
                         "(a box or the whole head?): the pose network reads the brain's outline; upload a brain "
                         "mask (`svrnet masks` makes one), or none")
        elif where.get("method") == "network" and float(where.get("confidence") or 0.0) < LOW_CONFIDENCE:
            hints.append(f"{name}: the localiser was unsure of the brain (confidence {where.get('confidence', 0):.2f}); "
                         "check its mask with `svrnet masks`, or upload one with --mask")
        hints += consistency_hints(name, stack)
        lost = [s.get("index") for s in brain if s.get("signal_lost")]
        if lost:
            hints.append(f"{name}: {len(lost)} slice(s) lost the brain's signal (a signal void, motion within the "
                         f"slice: {', '.join(str(k) for k in lost)}): no other stack's image checks their poses; "
                         "acquire them again if you need them")
        cut = [s.get("index") for s in brain if s.get("cut_by_field_of_view")]
        if cut:
            hints.append(f"{name}: the field of view ends inside the brain in {len(cut)} slice(s) "
                         f"({', '.join(str(k) for k in cut)}): the pose network saw part of a brain, and those poses "
                         "may be far off; acquire the stack again with a field of view that holds the whole head")
        noise = stack.get("noise") or {}
        if brain and noise.get("beyond_calibration"):
            added = float(noise.get("expected_error_added_mm") or 0.0)
            told = (f"its expected errors include {added:.2f} mm for the noise, so fewer of its slices are accepted"
                    if added > 0 else "its poses may be less accurate than their expected errors say, and some of its "
                                      "accepted slices wrong")
            hints.append(f"{name}: noisier than the pose network learnt (input noise "
                         f"{noise.get('input_noise') or 0:.3f}, a low-field scanner's): {told}; check its poses "
                         "against the other stacks' or acquire it again")
    slices = with_brain([s for st in stacks for s in st.get("slices") or []])
    one_pass = bool(slices) and all(s.get("reason") == "high_variance" and s.get("geodesic_variance") is None
                                    for s in slices)
    if stage_off and not one_pass and slices and sum(bool(s.get("accepted")) for s in slices) < len(slices) / 2:
        hints.append(f"fewer than half the slices accepted with {stage_off} off: the accept flags judge what every "
                     "stage makes of the poses, and without it most real slices' expected errors stay over the "
                     "limit; send the request with every stage on before you acquire anything again")
        return hints
    if usable(result):
        for stack in stacks:
            if with_brain(stack.get("slices") or []) and not any(s.get("accepted") for s in stack.get("slices") or []):
                if _mirrored(stack) or _apart_mm(stack) is not None:
                    continue                                  # said above, with what to do
                if stage_off:
                    hints.append(f"{stack.get('filename', '?')}: no slice accepted with {stage_off} off, while the "
                                 "other stacks have some: send the request with every stage on before you acquire "
                                 "it again")
                    continue
                fit = stack.get("consistency") or {}
                unplaced = fit.get("branch_from_request") and not fit.get("branch_agrees_with_request")
                hints.append(f"{stack.get('filename', '?')}: no slice accepted while the other stacks have some: " + (
                    "its slices do not tell its left-right branch and it sits with the other stacks on neither "
                    "(without a mask, a sagittal stack can); send masks with every stack (`svrnet masks` makes the others', "
                    "sent with --masks-hold-csf), or acquire it again"
                    if unplaced else
                    "its poses are too uncertain or disagree with the others (motion, a signal void); acquire it "
                    "again if you need it"))
    if one_pass:
        hints.append("no slice accepted: one MC pass measures no spread (geodesic_variance null), and a pose "
                     "without one is not judged usable; send --mc-samples 100, the count the accept flags are "
                     "calibrated at")
    frame = next((st.get("frame") for st in stacks if isinstance(st.get("frame"), dict)), None) or {}
    added, limit = float(frame.get("expected_error_added_mm") or 0.0), result.get("max_expected_error_mm")
    held_back = [s for s in slices if s.get("reason") == "high_expected_error" and limit is not None
                 and float(s.get("expected_error_mm") or 0.0) ** 2 - added ** 2 <= float(limit) ** 2]
    if not one_pass and added > 0 and len(held_back) >= len(slices) / 2:
        none = not any(s.get("accepted") for s in slices)
        found = any((st.get("localisation") or {}).get("method") == "network" for st in stacks)
        hints.append(("no slice accepted: " if none else "fewer slices accepted: ") +
                     f"every expected error includes {added:.2f} mm for the request's placement in the atlas as a "
                     f"whole (the network's poses scatter {frame.get('request_network_error_mm') or 0:.0f} mm about "
                     "the stacks' motion, more than on the scans the accept flags are calibrated on); the slices may "
                     "still agree with each other. Next: " + (
                         "send brain masks drawn by hand (`svrnet masks` makes drafts to correct: sent as they are, "
                         "they place the request as it is placed now)"
                         if found else
                         "masks drawn to the brain alone (sent without --masks-hold-csf), or to its skull's inside "
                         "(sent with it), place a request surer than masks that take in tissue beside the brain") +
                     "; or `svrnet reconstruct` these stacks: the job starts from the slices whose own errors pass "
                     "(one given these poses keeps their flags)")
        return hints
    if slices and not one_pass and not any(s.get("accepted") for s in slices):
        limit = result.get("max_expected_error_mm")
        why = (f" (every one expects an error over {limit:.3g} mm)"
               if limit is not None and all(s.get("reason") == "high_expected_error" for s in slices) else "")
        disagree = [st.get("filename", "?") for st in stacks if (st.get("consistency") or {}).get("decidable") is False
                    or (st.get("image_consistency") or {}).get("agreed") is False
                    or any(s.get("reason") == "inconsistent_with_stack" for s in st.get("slices") or [])]
        hints.append(f"no slice accepted{why}: " + (
            "a stack sent alone has no other stack to agree with; send all the stacks of a scan in one request "
            "(if nothing is accepted then either, the images are the cause: see the reasons above)"
            if len(stacks) == 1 else
            f"the slices do not agree on where they lie ({', '.join(disagree)}: motion beyond the model's reach, "
            "signal voids, a contrast unlike T2), so no pose is worth using; see the reasons above"
            if disagree else
            f"the network is unsure where these slices lie{median_of(slices)}; brain masks drawn by hand often "
            "help where the service's own (or the ones sent) take in tissue beside the brain; a reconstruction job "
            "(`svrnet reconstruct`) starts from every slice where its request has few accepted"))
    return hints


def median_of(slices: list[dict[str, Any]]) -> str:
    """`` (their median expected error X mm)`` of ``slices`` that have one; empty where none has.

    Example:
        >>> median_of([{"expected_error_mm": 6.0}, {"expected_error_mm": 9.0}, {"expected_error_mm": None}])
        ' (their median expected error 7.5 mm)'
    """
    expected = [float(s["expected_error_mm"]) for s in slices if s.get("expected_error_mm") is not None]
    return f" (their median expected error {statistics.median(expected):.1f} mm)" if expected else ""


@contextmanager
def upload_bar(console: Console, label: str) -> Iterator[Callable[[int, int], None]]:
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


def masks_table(report: list[dict[str, Any]], out_dir: object) -> Table:
    """The table of ``svrnet masks``: one row per stack of a ``/v1/masks`` report (api-v1's list of
    per-stack objects). File names fold rather than being cut short, so that the table fits an
    80-column terminal."""
    table = Table(title=f"brain masks in {out_dir}", title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False,
                  collapse_padding=True, caption_justify="left",
                  caption="volume: the mask's, the skull's inside (brain and the CSF around it: intracranial, not "
                          "the brain alone); slices: those the mask touches "
                          "(`svrnet predict` calls a slice empty below 1 % of its network input)")
    for col, just in (("stack", "left"), ("mask", "left"), ("volume (ml)", "right"), ("confidence", "right"),
                      ("slices", "right")):
        table.add_column(col, justify=just, overflow="fold")  # type: ignore[arg-type]
    for row in report:
        table.add_row(str(row.get("filename", "")), str(row.get("mask", "")),
                      f"{row.get('brain_volume_ml', 0):.0f}", f"{row.get('confidence', 0):.2f}",
                      str(row.get("slices_with_brain", "")))
    return table


def models_table(listed: list[dict[str, Any]]) -> Table:
    """The table of ``svrnet models``: one row per model the server offers, with the two thresholds that
    decide ``accepted``; it fits an 80-column terminal (the training volumes are in ``--json``)."""
    table = Table(box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True, caption_justify="left",
                  caption="accepted: expected error (mm) and variance at most these, unless a request says otherwise; "
                          "the training data and its licences: --json")
    for col in ("name", "version", "backbone", "max expected error", "variance", "sha256"):
        table.add_column(col, overflow="fold")
    for m in listed:
        limit, threshold = m.get("max_expected_error_mm"), m.get("variance_threshold")
        table.add_row(str(m.get("name", "")), str(m.get("version", "")), str(m.get("backbone", "")),
                      "-" if limit is None else f"{limit:g} mm", "-" if threshold is None else f"{threshold:g}",
                      str(m.get("sha256", ""))[:12])
    return table
