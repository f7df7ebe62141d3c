"""What ``svrnet stream`` shows: the growing table of the open stack's poses, each finished stack's
table and lines, built from the stream's messages (``stream-v1``).

Nothing here talks to a server: each table or line is built from a message (a dict), so the
command's output is tested on messages alone.

Example:
    >>> coverage_text({"brain_fraction": 0.5, "gaps": []})
    '50% of the brain, 0 gaps'
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from rich import box
from rich.console import Console
from rich.table import Table

from client.views import consistency_hints, with_brain

if TYPE_CHECKING:                     # client.stream needs numpy and nibabel: imported by `svrnet stream` only
    from client.stream import Sent


class StreamView:
    """What ``svrnet stream`` shows: a table of the open stack's slices that grows as poses arrive
    (``renderable``, for :class:`rich.live.Live`), and, printed above it, each finished stack's table,
    a line on its acceptance and coverage, the slices of finished stacks that a later one moved, and
    the server's errors in red."""

    def __init__(self, console: Console) -> None:
        self.console = console
        self.rows: dict[tuple[str, int], dict[str, Any]] = {}    # (stack, index) -> the row's fields
        self.finished: set[str] = set()                           # stacks whose `stack` message came
        self.limit: float | None = None                           # the session's accept limit (mm)
        self.hinted: set[str] = set()                             # consistency hints printed

    def on_message(self, message: dict[str, Any], answered: Sent | None) -> None:
        kind = message.get("type")
        if kind == "ready":
            model = message.get("model") or {}
            limit = self.limit = message.get("max_expected_error_mm")
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
            if name in self.finished and message.get("slices"):
                self.console.print(f"update of stack {name}: " + ", ".join(
                    f"#{s.get('index')} {' '.join(pose_cells(s, self.limit)[2:4])}" for s in message.get("slices") or []),
                    markup=False)
            if name in self.finished and "consistency" in message:
                self.print_hints(name, message)
            if name in self.finished and "reacquire" in message:
                rows = [row for (stack, _), row in self.rows.items() if stack == name]
                self.console.print(f"stack {name} now: {accepted_text(rows)} · "
                                   f"reacquire: {reacquire_text(message['reacquire'])}", markup=False)
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
        alone = " (judged alone: the next stack that crosses it can accept its slices)" if message.get("judged_alone") else ""
        self.console.print(f"stack {name}: {accepted_text(final)}{alone} · "
                           f"reacquire: {reacquire_text(message.get('reacquire'))} · "
                           f"coverage {coverage_text(message.get('coverage'))}", markup=False)
        self.print_hints(name, message)

    def print_hints(self, name: str, message: dict[str, Any]) -> None:
        """What to do about a stack the session left out of its decisions (mirrored, another fetus's:
        :func:`~client.views.consistency_hints`), once each, as its ``stack`` or a later ``update`` says."""
        for hint in consistency_hints(f"stack {name}", message):
            if hint not in self.hinted:
                self.hinted.add(hint)
                self.console.print(hint, style="yellow", markup=False)

    def table(self, rows: list[dict[str, Any]], title: str | None = None) -> Table:
        """Poses as rows that fit an 80-column terminal (stack names fold; nothing is cut short)."""
        table = Table(title=title, title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True,
                      caption="#: slice index, * its pose updated by later slices; translation: atlas mm",
                      caption_justify="left")
        for col, just in (("stack", "left"), ("#", "right"), ("accepted", "left"), ("expected error", "right"),
                          ("translation", "right"), ("latency", "right")):
            table.add_column(col, justify=just, overflow="fold",  # type: ignore[arg-type]
                             max_width=14 if col == "stack" else None, no_wrap=col in ("accepted", "translation"))
        for row in rows:
            table.add_row(*pose_cells(row, self.limit))
        return table

    def print_open(self) -> None:
        """Print the slices of the stacks that did not end (a session cut short): what was received
        stays on the screen and in a redirected output, not only in ``--json-out``."""
        rows = [row for (stack, _), row in self.rows.items() if stack not in self.finished]
        if rows:
            self.console.print(self.table(rows, "received before the session ended (no final poses)"))

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


def pose_cells(row: dict[str, Any], limit: float | None = None) -> list[str]:
    """A pose's cells in ``svrnet stream``'s table (the index marked ``*`` once a later slice updated
    the pose; the translation to the millimetre: the JSON output has it in full); the expected error
    to 0.1 mm, or finer where that would put it on the other side of the accept ``limit``.

    Example:
        >>> pose_cells({"stack": "ax", "index": 3, "accepted": False, "reason": "high_expected_error",
        ...             "expected_error_mm": 7.25, "translation_mm": [1, -2.5, 30], "latency_ms": 21.4, "updated": True})
        ['ax', '3*', '✗ high_expected_error', '7.2 mm', '(1, -2, 30)', '21 ms']
        >>> pose_cells({"expected_error_mm": 4.82}, limit=4.8)[3]        # not "4.8 mm" beside a limit of 4.8
        '4.82 mm'
    """
    expected, translation, latency = row.get("expected_error_mm"), row.get("translation_mm"), row.get("latency_ms")
    return [str(row.get("stack", "")), f"{row.get('index', '')}{'*' if row.get('updated') else ''}",
            "✓" if row.get("accepted") else f"✗ {row.get('reason') or ''}".rstrip(),
            "-" if expected is None else f"{beside_limit(expected, limit)} mm",
            "-" if not translation else "(" + ", ".join(f"{v:.0f}" for v in translation) + ")",
            "-" if latency is None else f"{latency:.0f} ms"]


def beside_limit(value: float, limit: float | None) -> str:
    """``value`` to 0.1, or to as many more decimals (up to 3) as keep it on its side of ``limit``.

    Example:
        >>> beside_limit(4.83, 4.8), beside_limit(4.75, 4.8), beside_limit(7.25, 4.8), beside_limit(4.8, None)
        ('4.83', '4.8', '7.2', '4.8')
    """
    for digits in (1, 2, 3):
        text = f"{value:.{digits}f}"
        if limit is None or (float(text) > limit) == (value > limit):
            return text
    return text


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


def accepted_text(slices: list[dict[str, Any]]) -> str:
    """How many of a stack's slices with brain are accepted, counted as ``svrnet predict`` counts them
    (an ``empty`` slice has no pose to accept).

    Example:
        >>> accepted_text([{"accepted": True}, {"accepted": False, "reason": "empty"}, {"accepted": False}])
        '1 of 2 slices with brain accepted'
    """
    brain = with_brain(slices)
    return f"{sum(1 for s in brain if s.get('accepted'))} of {len(brain)} slices with brain accepted"


def coverage_text(coverage: dict[str, Any] | None) -> str:
    """The coverage of the atlas brain in words (none covered: no gaps to count, the whole brain is one).

    Example:
        >>> coverage_text({"brain_fraction": 0.834, "gaps": [{"extent_mm": 12.0}]})
        '83% of the brain, 1 gap'
        >>> coverage_text({"brain_fraction": 0.0, "gaps": []})
        'none of the brain (no slice accepted)'
    """
    coverage = coverage or {}
    fraction, gaps = coverage.get("brain_fraction"), len(coverage.get("gaps") or [])
    if fraction is not None and fraction <= 0:
        return "none of the brain (no slice accepted)"
    return f"{'-' if fraction is None else f'{fraction:.0%}'} of the brain, {gaps} gap{'' if gaps == 1 else 's'}"
