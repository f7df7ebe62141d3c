"""The file parts an upload sends: stack and mask files, and a folder of one DICOM series as its ``.zip``.

Kept apart from the HTTP client: what an upload sends depends on the files alone, and is testable
without a server (:mod:`client.multipart` frames the body).

Example:
    >>> import tempfile
    >>> d = Path(tempfile.mkdtemp()); _ = (d / "ax.nii.gz").write_bytes(b"x"); _ = (d / "ax_mask.nii.gz").write_bytes(b"")
    >>> [(field, name, ctype) for field, name, _, ctype in file_parts(d / "ax.nii.gz", d / "ax_mask.nii.gz")]
    [('stacks', 'ax.nii.gz', 'application/octet-stream'), ('masks', 'ax_mask.nii.gz', 'application/octet-stream')]
"""

from __future__ import annotations

import io
import os
import zipfile
from collections.abc import Sequence
from pathlib import Path

from client.errors import ArgumentError
from client.transport import PathLike

__all__ = ["MAX_FOLDER_BYTES", "VOLUME_SUFFIXES", "file_parts", "zipped_folder"]

MAX_FOLDER_BYTES = 512 << 20
"""The most a folder of one DICOM series may hold to be sent (zipped in memory; the server's default
upload limit)."""
VOLUME_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd", ".hdr", ".img", ".zip")
"""Files that are whole stacks (or an archive of one series) in themselves: a folder holding them is
no DICOM series, and is refused with the files to give instead."""


def zipped_folder(folder: Path) -> bytes:
    """A folder of one DICOM series as the ``.zip`` the server takes: its files (sub-folders
    included; hidden files and links not, so nothing outside the folder goes), stored under their
    paths in it.

    Raises:
        ArgumentError: naming the folder, when it holds no file, more than :data:`MAX_FOLDER_BYTES`, or
            files that are stacks in themselves (:data:`VOLUME_SUFFIXES`: a folder of NIfTI stacks).

    Example:
        >>> import tempfile
        >>> d = Path(tempfile.mkdtemp()); _ = (d / "IM0001.dcm").write_bytes(b"x"); _ = (d / ".DS_Store").write_bytes(b"")
        >>> zipfile.ZipFile(io.BytesIO(zipped_folder(d))).namelist()
        ['IM0001.dcm']
    """
    files = sorted(p for p in folder.rglob("*")
                   if p.is_file() and not p.is_symlink()
                   and not any(part.startswith(".") for part in p.relative_to(folder).parts))
    if not files:
        raise ArgumentError(f"stacks: the folder {folder} holds no file")
    volumes = [p for p in files if p.name.lower().endswith(VOLUME_SUFFIXES)]
    if volumes:
        shown = ", ".join(p.name for p in volumes[:4]) + (", ..." if len(volumes) > 4 else "")
        raise ArgumentError(f"stacks: the folder {folder} holds image files ({shown}); a folder is sent as one "
                            f"DICOM series: give its stacks as files instead ({folder / '*.nii.gz'})")
    if sum(p.stat().st_size for p in files) > MAX_FOLDER_BYTES:
        raise ArgumentError(f"stacks: the folder {folder} holds more than {MAX_FOLDER_BYTES >> 20} MB; send one series")
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        for p in files:
            archive.write(p, p.relative_to(folder).as_posix())
    return buffer.getvalue()


def file_parts(stacks: Sequence[PathLike], masks: Sequence[PathLike] | None) -> list[tuple[str, str, Path | bytes, str]]:
    """The upload's file parts; a stack given as a folder (one DICOM series) goes as its ``.zip``."""
    if isinstance(stacks, (str, os.PathLike)):
        stacks = [stacks]
    if isinstance(masks, (str, os.PathLike)):
        masks = [masks]
    if not stacks:
        raise ArgumentError("stacks: at least one file is required")
    masks = list(masks or [])
    if masks and len(masks) != len(stacks):
        raise ArgumentError(f"masks: {len(masks)} given for {len(stacks)} stacks; give none or one per stack")
    files: list[tuple[str, str, Path | bytes, str]] = []
    for field, paths in (("stacks", stacks), ("masks", masks)):
        for p in paths:
            path = Path(p).expanduser()
            if field == "stacks" and path.is_dir():
                files.append((field, f"{path.resolve().name}.zip", zipped_folder(path), "application/zip"))
                continue
            if not path.is_file():
                raise FileNotFoundError(f"{field}: no such file: {path}")
            files.append((field, path.name, path, "application/octet-stream"))
    return files
