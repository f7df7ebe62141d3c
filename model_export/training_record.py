"""The record a training run leaves: its hardware, its code's commit, the segments behind a
checkpoint, totals over them, and the curves of its log.

Every checkpoint carries ``history``, one segment per run (hardware, device, samples, seconds, loss,
label, the ``commits`` its code was at); a model card states the totals, overall and per hardware,
and only what the checkpoints record.

Example:
    >>> totals(prior_history({"samples_seen": 64, "train_seconds": 7200.0}))["hours"]
    2.0
"""

from __future__ import annotations

import csv
import os
import subprocess
from pathlib import Path

import torch

UNRECORDED_HARDWARE = "not recorded"
"""The hardware of a training segment whose checkpoint does not record it (see :func:`prior_history`)."""


def hardware(device: torch.device) -> str:
    """A short description of what trains: the GPU's name, or the CPU's core count."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"CPU, {os.cpu_count()} cores"


CHECKOUT = Path(__file__).resolve().parents[1]
"""The checkout this code runs from (an installed package's parent folder is none)."""


def git_commit(repo: Path | None = None, short: bool = True) -> str:
    """The commit (``short``: abbreviated) of the repository holding ``repo``, with ``-dirty`` when a tracked file
    differs from it (staged or not); ``unknown`` outside git. Untracked files do not count
    (``git status --porcelain --untracked-files=no``): run folders, packed data and reports are
    untracked, while code a run imports is tracked once committed. Without ``repo``: this code's
    own checkout, ``unknown`` where the code is an installed package (a virtualenv inside some
    other repository must not lend it that repository's commit).

    Example:
        >>> import tempfile
        >>> git_commit(Path(tempfile.mkdtemp()))
        'unknown'
    """
    folder = CHECKOUT if repo is None else Path(repo)

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], capture_output=True, text=True, check=True, cwd=folder).stdout.strip()

    try:
        if repo is None and Path(git("rev-parse", "--show-toplevel")).resolve() != CHECKOUT:
            return "unknown"
        commit = git("rev-parse", *(["--short"] if short else []), "HEAD")
        return commit + ("-dirty" if git("status", "--porcelain", "--untracked-files=no") else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def commits(history: list[dict]) -> list[str]:
    """The commits of the code behind a checkpoint's segments, each once, oldest first (segments of
    runs that recorded none give none).

    Example:
        >>> commits([{"commits": ["a1b2c3d"]}, {}, {"commits": ["a1b2c3d", "e4f5a6b-dirty"]}])
        ['a1b2c3d', 'e4f5a6b-dirty']
    """
    return list(dict.fromkeys(c for seg in history for c in seg.get("commits", ())))


def totals(history: list[dict]) -> dict:
    """Samples and hours over all training segments, overall and per hardware.

    Example:
        >>> totals([{"hardware": "a", "samples": 10, "seconds": 3600}, {"hardware": "b", "samples": 5, "seconds": 0}])
        {'samples': 15, 'hours': 1.0, 'by_hardware': {'a': {'samples': 10, 'hours': 1.0}, 'b': {'samples': 5, 'hours': 0.0}}}
    """
    by: dict[str, dict] = {}
    for seg in history:
        d = by.setdefault(seg["hardware"], {"samples": 0, "hours": 0.0})
        d["samples"] += int(seg["samples"])
        d["hours"] += seg["seconds"] / 3600
    return {"samples": sum(d["samples"] for d in by.values()), "hours": sum(d["hours"] for d in by.values()),
            "by_hardware": by}


def prior_history(ck: dict) -> list[dict]:
    """The training segments behind a checkpoint, stating only what it records.

    A run records its own segment, with its ``run`` folder and its hardware. A checkpoint without a
    ``history`` records only its totals: they make one segment whose hardware is
    :data:`UNRECORDED_HARDWARE`, and a later checkpoint carries that segment on (the one without
    ``run``), so such a segment's hardware is read as unrecorded whatever label it carries.

    Example:
        >>> [seg["hardware"] for seg in prior_history({"samples_seen": 10, "train_seconds": 1.0})]
        ['not recorded']
        >>> [seg["hardware"] for seg in prior_history({"history": [{"hardware": "a label", "samples": 10},
        ...                                                        {"hardware": "CPU, 2 cores", "run": "r"}]})]
        ['not recorded', 'CPU, 2 cores']
    """
    if ck.get("history"):
        return [seg if "run" in seg else {**seg, "hardware": UNRECORDED_HARDWARE} for seg in ck["history"]]
    cfg = ck.get("config", {})
    return [{"hardware": UNRECORDED_HARDWARE, "device": "cpu", "samples": int(ck.get("samples_seen", 0)),
             "seconds": float(ck.get("train_seconds", 0.0)), "steps": int(ck.get("step", 0)),
             "label_type": cfg.get("label_type", "anchor"), "loss": cfg.get("loss", "l2")}]


def plot_log(log_path: Path, png: Path) -> None:
    """Loss and validation E.D. curves (truth and twin-min) from a training log (skipped without matplotlib)."""
    try:
        import matplotlib
    except ImportError:
        return

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(csv.DictReader(open(log_path)))
    if not rows:
        return
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
    ax[0].plot([int(r["samples"]) for r in rows], [float(r["loss"]) for r in rows])
    ax[0].set(xlabel="samples (total)", ylabel="loss (normalised)", yscale="log", title="training loss")
    val = [r for r in rows if r["val_ed_mm"]]
    ax[1].plot([int(r["samples"]) for r in val], [float(r["val_ed_mm"]) for r in val], "o-", label="E.D.")
    ax[1].plot([int(r["samples"]) for r in val], [float(r["val_twin_ed_mm"]) for r in val], "s-", label="twin-min E.D.")
    ax[1].set(xlabel="samples (total)", ylabel="mm", title="validation mean anchor E.D.")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
