"""The masks archive of ``POST /v1/masks`` written into a folder: one NIfTI mask per stack and
``report.json``, only the archive's own plain file names, each file whole or not at all; a folder's
report keeps the masks of earlier calls that stay beside it."""

from __future__ import annotations

import io
import json
import re
import zipfile
from pathlib import Path
from typing import Any

from client.errors import ArgumentError, SVRnetError
from client.files import write_whole

MAX_MASK_BYTES = 1 << 30
"""The largest archive member :meth:`SVRnetClient.masks` writes (a mask file of the server's)."""


REPORT = "report.json"
"""The masks' report, beside them (:meth:`SVRnetClient.masks`)."""


MASK_NAME_SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".nhdr", ".mha", ".mhd", ".dcm", ".zip", ".gz")
"""The extensions the server drops from a stack's name before ``_mask.nii.gz`` (api-v1: ``<stem>``)."""
MASK_SUFFIX = "_mask.nii.gz"
MAX_NAME = 255


def mask_names(stacks: list[Path]) -> list[str]:
    """The names api-v1 gives the masks of ``stacks``, sent as :meth:`SVRnetClient.masks` sends them
    (a folder as ``<folder>.zip``): ``<stem>_mask.nii.gz``, the stem the upload's name without its
    extensions, only ``[A-Za-z0-9._-]`` and no leading ``-``, made unique in order regardless of case
    with ``-1``, ``-2`` ..., at most 255 characters in all (the server's rule, written again: the
    client imports no server code).

    Example:
        >>> mask_names([Path("a/ax.nii.gz"), Path("b/AX.nii"), Path("x y.mha")])
        ['ax_mask.nii.gz', 'AX-1_mask.nii.gz', 'x_y_mask.nii.gz']
    """
    longest = MAX_NAME - len(MASK_SUFFIX)
    stems: list[str] = []
    for stack in stacks:
        path = Path(stack)
        base = (f"{path.resolve().name}.zip" if path.is_dir() else path.name).replace("\\", "/").rsplit("/", 1)[-1]
        base = next((base[:-len(x)] for x in MASK_NAME_SUFFIXES if base.lower().endswith(x)), base)
        stem = (re.sub(r"[^A-Za-z0-9._-]+", "_", base).lstrip("-._").rstrip("._") or "stack")[:longest]
        candidate, k = stem, 0
        while candidate.lower() in {s.lower() for s in stems}:
            k += 1
            candidate = f"{stem[:longest - len(str(k)) - 1]}-{k}"
        stems.append(candidate)
    return [stem + MASK_SUFFIX for stem in stems]


def masks_already_there(stacks: list[Path], out: Path) -> list[str]:
    """The masks in ``out`` that masks of ``stacks`` would replace (:func:`mask_names`): checked
    before the upload, and again as the archive is written (another server may name them otherwise).

    Example:
        >>> import tempfile
        >>> out = Path(tempfile.mkdtemp()); _ = (out / "ax-1_mask.nii.gz").write_bytes(b"")
        >>> masks_already_there([Path("scan/ax.nii.gz"), Path("old/ax.nii.gz")], out)
        ['ax-1_mask.nii.gz']
    """
    return [n for n in mask_names(stacks) if (out / n).exists()]


def report_entries(report: Any) -> list[dict[str, Any]]:
    """The per-stack objects of a masks report: api-v1's list, or the ``{"localiser", "stacks"}`` of
    this server before 2.12 (each entry then given its ``localiser``).

    Example:
        >>> report_entries({"localiser": {"version": "1.2.0"}, "stacks": [{"mask": "ax_mask.nii.gz"}]})
        [{'localiser': {'version': '1.2.0'}, 'mask': 'ax_mask.nii.gz'}]
    """
    if isinstance(report, dict):
        return [{"localiser": report.get("localiser"), **e} for e in report.get("stacks") or [] if isinstance(e, dict)]
    return [e for e in report if isinstance(e, dict)] if isinstance(report, list) else []


def _with_earlier_masks(report: Any, out: Path) -> list[dict[str, Any]]:
    """``report`` (of masks about to be written into ``out``) with the entries of the report already
    there whose masks stay: other masks of earlier calls, which the new report would otherwise hide,
    each with the ``localiser`` that made it.

    Example:
        >>> import tempfile
        >>> out = Path(tempfile.mkdtemp()); _ = (out / "ax_mask.nii.gz").write_bytes(b"")
        >>> _ = (out / REPORT).write_text(json.dumps([{"mask": "ax_mask.nii.gz"}, {"mask": "gone.nii.gz"}]))
        >>> [e["mask"] for e in _with_earlier_masks([{"mask": "co_mask.nii.gz"}], out)]
        ['ax_mask.nii.gz', 'co_mask.nii.gz']
    """
    entries = report_entries(report)
    try:
        earlier = report_entries(json.loads((out / REPORT).read_text()))
    except (OSError, ValueError):
        return entries
    new = {e.get("mask") for e in entries}
    kept = [e for e in earlier if isinstance(e.get("mask"), str) and e["mask"] not in new
            and e["mask"] == Path(e["mask"]).name and (out / e["mask"]).is_file()]
    return kept + entries


def write_mask_archive(content: bytes, out: Path, overwrite: bool, status: int | None = None,
                       request_id: str | None = None) -> list[dict[str, Any]]:
    """Write the masks archive ``content`` into ``out`` and return its report, an object per stack
    (joined with the folder's earlier one, :func:`_with_earlier_masks`). Masks of those names already there are kept,
    and nothing is written (:class:`ArgumentError`), unless ``overwrite``; an archive that cannot be
    read is the server's fault (:class:`SVRnetError` with ``status`` and ``request_id``)."""
    try:
        archive = zipfile.ZipFile(io.BytesIO(content))
        files = {i.filename: archive.read(i.filename) for i in archive.infolist()
                 if i.filename == Path(i.filename).name and i.filename.endswith((".nii.gz", ".json"))
                 and i.file_size <= MAX_MASK_BYTES}
        report = json.loads(files[REPORT])
    except (zipfile.BadZipFile, KeyError, ValueError) as exc:
        raise SVRnetError("the server's masks archive is unreadable", status=status, request_id=request_id) from exc
    there = [name for name in files if name != REPORT and (out / name).exists()]
    if there and not overwrite:
        raise ArgumentError(f"out_dir: {out} holds {', '.join(there)} already; nothing was written "
                            "(`svrnet masks --overwrite` replaces them; in Python, overwrite=True)")
    report = _with_earlier_masks(report, out)
    files[REPORT] = json.dumps(report, indent=1).encode()
    out.mkdir(parents=True, exist_ok=True)
    for name, data in files.items():
        write_whole(out / name, data)
    return report
