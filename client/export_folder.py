"""An export's folder: what an export wrote into it, and what ``--overwrite`` may remove.

NeSVoR reads every slice file of its folder and NiftyMIC every transform, so one patient's export
must never lie among another's (:func:`clear_for_export`); each export lists what it wrote
(:data:`MANIFEST`), and only that is ever removed.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from client.errors import ArgumentError
from client.files import write_whole

MANIFEST = ".svrnet-export.json"
"""The list of the files an export wrote into its folder: all that ``overwrite`` removes."""
TOOL_FILES = re.compile(r"^(.+\.nii(\.gz)?|.+\.tfm|slices\.tsv)$")
"""Names of the files of the folder itself (not of its subfolders) that either tool reads: NeSVoR
every ``*.nii`` and ``*.nii.gz`` (each a slice ``{i}`` or its ``mask_{i}``; any other name stops it),
NiftyMIC every ``NAME.tfm`` and ``NAME_slice{k}.tfm``."""


def folder_files(folder: Path) -> set[str]:
    """The files under ``folder``, as paths relative to it."""
    return {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()} if folder.is_dir() else set()


def clear_for_export(folder: Path, overwrite: bool, inputs: list[Path] = ()) -> set[str]:
    """Make ``folder`` ready for an export and return the files already there. Both tools read every
    slice file of the folder, so one patient's export must never lie among another's: a folder that
    holds anything is refused (:class:`~client.errors.ArgumentError`: the usage exit code) unless
    ``overwrite``, which removes what an earlier export listed in its :data:`MANIFEST` and nothing
    else, and then still refuses a folder
    holding files a tool would read (:data:`TOOL_FILES`) that no export listed. A folder that holds
    one of the ``inputs`` (the stacks and masks exported) is refused.

    Example:
        >>> import tempfile
        >>> d = Path(tempfile.mkdtemp()); _ = (d / "0.nii.gz").write_bytes(b""); _ = (d / "notes.txt").write_text("")
        >>> _ = (d / MANIFEST).write_text('["0.nii.gz"]')
        >>> sorted(clear_for_export(d, overwrite=True))
        ['notes.txt']
    """
    folder = folder.expanduser()
    inside = [p for p in inputs if folder.resolve() in Path(p).expanduser().resolve().parents]
    if inside:
        raise ArgumentError(f"out_dir: {inside[0].name} lies in the folder to write, {folder}; give another folder")
    if not folder_files(folder):
        folder.mkdir(parents=True, exist_ok=True)
        return set()
    if not overwrite:
        raise ArgumentError(f"out_dir: {folder} is not empty; each tool reads every slice file of its folder, so "
                            "give a new or empty folder (--overwrite replaces an earlier export there)")
    try:
        listed = json.loads((folder / MANIFEST).read_text()) if (folder / MANIFEST).is_file() else []
    except (OSError, ValueError):
        listed = []
    root = folder.resolve()
    for name in listed if isinstance(listed, list) else []:
        relative = Path(str(name))
        path = folder / relative
        # a manifest copied, shared or edited may name anything: only a file inside the folder goes
        # (not an absolute name, nor one through ".." or a linked subfolder)
        if not relative.is_absolute() and ".." not in relative.parts and root in path.resolve().parents \
                and path.is_file():
            path.unlink()
    (folder / MANIFEST).unlink(missing_ok=True)
    left = sorted(n for n in folder_files(folder) if "/" not in n and TOOL_FILES.match(n))
    if left:
        raise ArgumentError(f"out_dir: {folder} holds {left[0]}, a file a tool would read that no export of svrnet "
                            "wrote; give a new or empty folder")
    return folder_files(folder)


def write_manifest(folder: Path, before: set[str]) -> None:
    """List in :data:`MANIFEST` the files of ``folder`` that an export wrote: those not among ``before``
    (what :func:`clear_for_export` found there)."""
    write_whole(folder / MANIFEST, json.dumps(sorted(folder_files(folder) - before - {MANIFEST}), indent=0).encode())
