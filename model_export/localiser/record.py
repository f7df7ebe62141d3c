"""What a localiser checkpoint records of its making: the code, the data and the file itself.

A training run (:func:`~model_export.localiser.train.train`) writes :func:`git_state` and
:func:`data_record` of its shard folder into the checkpoint; ``ship`` writes :func:`file_record` of
the checkpoint beside the model. None of them holds an absolute path: a shard folder is named by
its last component and identified by the hash of its shards' names and contents.

Example:
    >>> import tempfile
    >>> folder = Path(tempfile.mkdtemp()) / "shards"
    >>> folder.mkdir()
    >>> data_record(folder, shard_manifest(folder, {}))["shards"]
    0
    >>> seed_ranges([3, 0, 1, 2, 7])
    '0-3, 7'
"""

from __future__ import annotations

import hashlib
import json
import re
import zipfile
from pathlib import Path

import numpy as np

from model_export.training_record import git_commit
from service.core.checksum import file_sha256



def git_state(repo: Path | None = None) -> str:
    """The whole commit the code runs at (or ``repo``'s), with ``-dirty`` when tracked files have
    uncommitted changes (``unknown`` outside a checkout; :func:`~model_export.training_record.git_commit`)."""
    return git_commit(repo, short=False)


def file_record(path: Path) -> dict:
    """A file's name (not its folder), size and sha256."""
    return {"name": Path(path).name, "bytes": Path(path).stat().st_size, "sha256": file_sha256(path)}


def shard_manifest(folder: Path, known: dict[str, dict]) -> dict[str, dict]:
    """``known`` with every whole shard of ``folder`` not in it yet: its sha256, grid and generator
    settings (None for a shard made before they were recorded). A shard still being written is
    skipped (a later call takes it); shards are never rewritten, so each is hashed once."""
    for path in sorted(Path(folder).glob("*.npz")):
        if path.name in known:
            continue
        try:
            with np.load(path) as z:
                grid = float(z["grid_mm"]) if "grid_mm" in z else None
                generator = json.loads(str(z["generator"])) if "generator" in z else None
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            continue
        known[path.name] = {"sha256": file_sha256(path), "grid_mm": grid, "generator": generator}
    return known


def seed_ranges(seeds: list[int]) -> str:
    """Seeds as runs of consecutive numbers (``0-599, 10000``)."""
    seeds, runs = sorted(set(seeds)), []
    for s in seeds:
        if runs and s == runs[-1][1] + 1:
            runs[-1][1] = s
        else:
            runs.append([s, s])
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs)


def data_record(folder: Path, manifest: dict[str, dict]) -> dict:
    """The identity of a shard folder: its name, its shards' names, the sha256 of its manifest (one
    ``name sha256`` line per shard, by name) and the generator settings of its shards, grouped, with
    the seeds of each group (from the shard names, ``<style>-<seed>.npz``)."""
    names = sorted(manifest)
    lines = "".join(f"{n} {manifest[n]['sha256']}\n" for n in names)
    groups: dict[str, list[int]] = {}
    for n in names:
        key = json.dumps(manifest[n]["generator"], sort_keys=True)
        match = re.search(r"(\d+)\.npz$", n)
        groups.setdefault(key, []).extend([int(match.group(1))] if match else [])
    return {"folder": Path(folder).name, "shards": len(names), "names": names,
            "manifest_sha256": hashlib.sha256(lines.encode()).hexdigest(),
            "generators": [{"settings": json.loads(k), "shards": len(v), "seeds": seed_ranges(v)}
                           for k, v in groups.items()]}
