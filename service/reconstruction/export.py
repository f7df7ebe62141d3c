"""Writing a reconstruction: volume, preview, per-slice transforms (ITK ``.tfm`` and a text listing, and
both in ``transforms.zip``), report.

Per-slice ``.tfm`` files (``transforms/stack{S}_slice{K:03d}.tfm``) hold an
``AffineTransform_double_3_3`` in ITK's LPS world frame with centre 0. The mapping is exactly

    T_lps = F @ scanner_from_atlas @ F,   scanner_from_atlas = stack_affine @ inverse(atlas_from_voxel),

with ``F = diag(-1, -1, 1, 1)`` (:mod:`service.geometry.frames`): it maps a point of the
reconstruction / atlas space (LPS mm) to the point of the uploaded stack's own physical space
(LPS mm, as the service placed that file: a NIfTI file by its sform whenever its code is above 0)
where that slice observed it. This is ITK's registration
convention with the reconstruction as the fixed image and the stack as the moving image, so
``sitk.Resample(stack_image, reconstruction_image, sitk.ReadTransform(path))`` maps that slice of
the stack into atlas space. (``atlas_from_scanner``, the other direction, is its inverse.)

``transforms/slice_transforms.txt`` lists every slice, one line each:
``stack slice included weight`` then the 12 numbers of the top 3 x 4 block (row-major) of
``atlas_from_voxel`` (voxel index of the stack file -> atlas RAS mm). ``report.json`` has the same
per slice with the NCC, plus the volume's geometry, each stack's frame (``stack_frames``:
:mod:`service.reconstruction.stack_space`) and the timings.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import threading
import zipfile
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from service.geometry import frames
from service.io.nifti_header import (ALIGNED_ANAT, NiftiTransforms, copy_transforms, placed_by, read_transforms, set_codes,
                                     sform_affine)
from service.io.volume import write_volume
from service.reconstruction.pipeline import ReconstructionResult
from service.reconstruction.preview import preview_png
from service.reconstruction.slices import SliceSet
from service.reconstruction.stack_space import (in_stack_space, scanner_from_atlas, stack_frame, stack_frames,
                                                with_header)

TFM_HEADER = "#Insight Transform File V1.0"


def tfm_text(transform_lps: ArrayLike) -> str:
    """The ``.tfm`` text of one ``4 x 4`` world -> world affine given in LPS."""
    m = np.asarray(transform_lps, dtype=np.float64)
    params = " ".join(repr(float(v)) for v in list(m[:3, :3].ravel()) + list(m[:3, 3]))
    return (f"{TFM_HEADER}\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
            f"Parameters: {params}\nFixedParameters: 0 0 0\n")


def zip_folder(folder: Path, target: Path) -> Path:
    """The files of ``folder`` in one zip archive ``target`` (deflated, named ``<folder>/<file>`` in
    it, sorted), as ``GET /v1/reconstructions/{id}/transforms`` serves a job's transforms.

    Example:
        >>> import tempfile, zipfile
        >>> d = Path(tempfile.mkdtemp()); (d / "t").mkdir(); _ = (d / "t" / "a.tfm").write_text("x")
        >>> zipfile.ZipFile(zip_folder(d / "t", d / "t.zip")).namelist()
        ['t/a.tfm']
    """
    partial = Path(target).with_name(f".{Path(target).name}.{os.getpid()}.{threading.get_ident()}")
    with zipfile.ZipFile(partial, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for path in sorted(Path(folder).iterdir()):
            if path.is_file():
                archive.write(path, f"{Path(folder).name}/{path.name}")
    os.replace(partial, target)                  # whole or absent: a reader never sees a partial archive
    return Path(target)


def write_slice_tfms(folder: Path, atlas_from_voxel: ArrayLike, slices: SliceSet) -> list[Path]:
    """Write one ``.tfm`` per slice (see the module docstring for the mapping); returns the paths."""
    folder.mkdir(parents=True, exist_ok=True)
    lps = frames.LPS_FROM_RAS @ scanner_from_atlas(atlas_from_voxel, slices.stack_affine) @ frames.RAS_FROM_LPS
    paths = []
    for i, m in enumerate(lps):
        path = folder / f"stack{int(slices.stack_index[i])}_slice{int(slices.slice_index[i]):03d}.tfm"
        path.write_text(tfm_text(m))
        paths.append(path)
    return paths


def _num(v: float) -> float | None:
    return None if v is None or not math.isfinite(float(v)) else float(v)


def slice_records(result: ReconstructionResult, slices: SliceSet) -> list[dict]:
    """Per-slice report entries (stack, slice, included, exclusion_reason, weight, ncc, held_out_ncc,
    atlas_from_voxel)."""
    reasons = result.exclusion_reason or [None if inc else "excluded" for inc in result.included.tolist()]
    held = result.held_out_ncc if result.held_out_ncc is not None else np.full(slices.n_slices, np.nan)
    return [{"stack": int(slices.stack_index[i]), "slice": int(slices.slice_index[i]),
             "included": bool(result.included[i]), "exclusion_reason": reasons[i],
             "weight": _num(result.slice_weight[i]),
             "ncc": _num(result.ncc[i]), "held_out_ncc": _num(held[i]),
             "atlas_from_voxel": result.atlas_from_voxel_final[i].tolist()}
            for i in range(slices.n_slices)]


def listing_text(result: ReconstructionResult, slices: SliceSet) -> str:
    """The per-slice listing (see the module docstring)."""
    lines = ["# stack slice included weight  atlas_from_voxel[0:3, 0:4] row-major "
             "(voxel index of the stack file -> atlas RAS mm)"]
    for i in range(slices.n_slices):
        mat = " ".join(f"{v:.9g}" for v in result.atlas_from_voxel_final[i, :3, :].ravel())
        lines.append(f"{int(slices.stack_index[i])} {int(slices.slice_index[i])} {int(bool(result.included[i]))} "
                     f"{float(result.slice_weight[i]):.6f} {mat}")
    return "\n".join(lines) + "\n"


def write_outputs(result: ReconstructionResult, slices: SliceSet, folder: str | Path, extra: dict | None = None,
                  more_files: tuple[str, ...] = (), stack_headers: list[NiftiTransforms | None] | None = None) -> dict:
    """Write ``volume.nii.gz`` (its NIfTI codes :data:`~service.io.nifti_header.ALIGNED_ANAT`: atlas
    coordinates), ``preview.png``, ``report.json`` and ``transforms/`` into ``folder``.

    Args:
        result: the reconstruction.
        slices: the slice set it was computed from (for stack/slice indices and stack headers).
        folder: output folder (created).
        extra: more entries for the report (e.g. the job's ``atlas_frame``).
        more_files: files the caller writes into ``folder`` after these, listed with them in the
            report's ``files``.
        stack_headers: each stack's NIfTI transforms (None: not read from NIfTI), kept in its
            ``stack_frames`` entry for the volume placed in its coordinates.

    Returns:
        The JSON-ready report (counts, geometry, timings, file names and, per slice, inclusion, weight
        and final pose) that is also written to ``report.json``; the job record holds it.
    """
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    write_volume(result.volume, out / "volume.nii.gz")
    set_codes(out / "volume.nii.gz", ALIGNED_ANAT)          # atlas coordinates, not the scanner's
    (out / "preview.png").write_bytes(preview_png(result.volume))
    tfms = write_slice_tfms(out / "transforms", result.atlas_from_voxel_final, slices)
    (out / "transforms" / "slice_transforms.txt").write_text(listing_text(result, slices))
    zip_folder(out / "transforms", out / "transforms.zip")
    ncc = result.ncc[result.included]
    headers = dict(enumerate(stack_headers or []))
    summary = {
        "n_stacks": int(slices.stack_index.max()) + 1 if slices.n_slices else 0,
        "n_slices": int(slices.n_slices),
        "n_included": int(result.included.sum()),
        "n_excluded": int((slices.include & ~result.included).sum()),
        "n_not_used": int((~slices.include).sum()),
        "slice_thickness_mm": [round(float(slices.thickness_mm[slices.stack_index == s][0]), 6)
                               for s in range(int(slices.stack_index.max()) + 1 if slices.n_slices else 0)],
        "excluded_by_reason": {r: (result.exclusion_reason or []).count(r)
                               for r in sorted({x for x in (result.exclusion_reason or []) if x})},
        "mean_ncc": _num(float(np.mean(ncc))) if ncc.size else None,
        "quality": result.quality,
        "intensity": None if result.intensity is None else result.intensity.summary(result.included),
        "shape": [int(s) for s in result.volume.array.shape],
        "resolution_mm": [float(s) for s in result.volume.spacing],
        "affine": result.volume.affine.tolist(),
        "stack_frames": [with_header(frame, headers.get(frame.stack)).as_json()
                         for frame in stack_frames(result.atlas_from_voxel_final, slices.stack_affine,
                                                   slices.stack_index, np.where(result.included, result.slice_weight,
                                                                                0.0))],
        "timings_s": {k: round(float(v), 3) for k, v in result.timings.items()},
        "files": ["volume.nii.gz", "preview.png", "report.json", "transforms/slice_transforms.txt",
                  f"transforms/*.tfm ({len(tfms)})", "transforms.zip", *more_files],
    }
    mapping = "LPS, atlas (fixed) -> stack scanner space (moving); see service.reconstruction.export"
    report = dict(summary, **(extra or {}), tfm_mapping=mapping, slices=slice_records(result, slices))
    (out / "report.json").write_text(json.dumps(report, indent=1))
    return report


def volume_in_stack_space(volume_path: Path, report: dict, stack: int, target: Path) -> Path:
    """A job's volume (``volume.nii.gz`` at ``volume_path``) placed in the scanner coordinates of its
    stack ``stack`` (the report's ``stack_frames``; :mod:`service.reconstruction.stack_space`), written
    to ``target`` (the caller's scratch file, never beside the job's files): the same voxels,
    another affine. Raises :class:`~service.reconstruction.stack_space.NoStackFrame` where the job has
    no such stack or no place for it, OSError where the volume is gone."""
    frame = stack_frame(report, stack)
    stored = read_transforms(volume_path)
    if stored is None:
        raise OSError(f"{volume_path.name}: no NIfTI-1 header")
    sform = in_stack_space(sform_affine(stored), frame)
    shutil.copyfile(volume_path, target)           # the voxels as stored: only the header changes
    if frame.nifti_codes is None:                  # scanner coordinates, both transforms alike
        copy_transforms(target, placed_by(sform, sform, 1, 1))
    else:                                          # the stack's header: read by its qform, the volume is too
        qform = sform if frame.qform_from_sform is None else frame.qform_from_sform @ sform
        copy_transforms(target, placed_by(sform, qform, *frame.nifti_codes, spatial_unit=frame.nifti_spatial_unit or 2))
    return target
