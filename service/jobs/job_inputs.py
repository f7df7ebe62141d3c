"""A job's stacks and masks as they wait for a worker: the decoded voxels, never the files as sent.

A reconstruction job's uploads are read and checked when it is submitted; a worker runs it later,
perhaps on another host sharing the data folder. What it needs of each stack is the
:class:`~service.io.volume.Volume` the submission read (its voxels, their placement, the acquisition
order and slice thickness its file stated) and its mask on the stack's grid, so that is what the
job folder keeps (``inputs/stack{i}.npz``, ``inputs/mask{i}.npz``): a DICOM file's header, with the
patient's name, identifiers and dates, is gone once the submission has been checked, as it is from
every other answer the service gives.

Example:
    >>> import tempfile
    >>> from pathlib import Path
    >>> vol = Volume(np.arange(24, dtype=np.float32).reshape(2, 3, 4), np.diag([1.0, 1.0, 3.0, 1.0]),
    ...              acquisition_order=(0, 2, 1, 3), slice_thickness_mm=2.5)
    >>> folder = Path(tempfile.mkdtemp())
    >>> keep_volume(vol, folder / "stack0.npz")
    >>> back = load_volume(folder / "stack0.npz")
    >>> bool(np.array_equal(back.array, vol.array)), back.acquisition_order, back.slice_thickness_mm
    (True, (0, 2, 1, 3), 2.5)
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from service.io.limits import raise_if_out_of_space
from service.io.nifti_header import NiftiTransforms
from service.io.volume import Volume

if TYPE_CHECKING:
    from service.pipeline.prepare import StackUpload


def keep_volume(volume: Volume, path: Path) -> None:
    """Write ``volume``'s voxels, affine, acquisition order, slice thickness, slice axis and the
    transforms of its NIfTI header (where it was read from one: how other readers place the stack) to
    ``path`` (``.npz``; nothing else of the file it was read from)."""
    order = np.asarray(volume.acquisition_order if volume.acquisition_order is not None else [], np.int64)
    try:
        np.savez(path, array=volume.array, affine=np.asarray(volume.affine, np.float64), acquisition_order=order,
                 has_order=volume.acquisition_order is not None,
                 slice_thickness_mm=np.nan if volume.slice_thickness_mm is None else volume.slice_thickness_mm,
                 slice_axis=-1 if volume.slice_axis is None else volume.slice_axis,
                 nifti=json.dumps(None if volume.nifti is None else asdict(volume.nifti)))
    except OSError as exc:
        raise_if_out_of_space(exc)        # a full disk is the server's (507)
        raise


def keep_json(value: object, path: Path) -> None:
    """Write ``value`` as JSON to ``path`` (a job's ``params.json``, ``names.json``, ``poses.json``); a
    full disk is the server's (507), as for the stacks."""
    try:
        path.write_text(json.dumps(value))
    except OSError as exc:
        raise_if_out_of_space(exc)
        raise


def load_volume(path: Path) -> Volume:
    """The :class:`Volume` :func:`keep_volume` wrote to ``path``."""
    with np.load(path, allow_pickle=False) as kept:
        thickness, axis = float(kept["slice_thickness_mm"]), int(kept["slice_axis"])
        fields = json.loads(str(kept["nifti"])) if "nifti" in kept.files else None     # a job queued before it
        nifti = None if fields is None else NiftiTransforms(
            **{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()})
        return Volume(kept["array"], kept["affine"],
                      tuple(int(k) for k in kept["acquisition_order"]) if bool(kept["has_order"]) else None,
                      slice_thickness_mm=None if np.isnan(thickness) else thickness,
                      slice_axis=None if axis < 0 else axis, nifti=nifti)


def keep_decoded(uploads: list[StackUpload], inputs: Path) -> None:
    """Each checked upload's stack (``stack{i}.npz``) and mask on its grid (``mask{i}.npz``) in the job's
    ``inputs``, and the files as sent (``stack{i}``, ``mask{i}``) deleted."""
    for i, upload in enumerate(uploads):
        keep_volume(upload.volume, inputs / f"stack{i}.npz")
        if upload.mask is not None:
            keep_volume(upload.mask, inputs / f"mask{i}.npz")
    for sent in [*inputs.glob("stack*"), *inputs.glob("mask*")]:
        if sent.suffix != ".npz":
            sent.unlink()


def decoded_files(inputs: Path) -> list[tuple[Path, Path | None]]:
    """The job's kept stacks and their masks (None: none), in upload order."""
    stacks = sorted(inputs.glob("stack*.npz"), key=lambda p: int(p.stem[5:]))
    return [(s, m if (m := inputs / f"mask{s.stem[5:]}.npz").exists() else None) for s in stacks]
