"""A ``/v1/predict`` answer's slice poses as ITK transforms, the files a reconstruction job writes.

ITK and SimpleITK read ``.tfm`` files (NiftyMIC's per-slice files are the inverse transforms, named
by stack: :mod:`client.peer_exports`). :func:`write_transforms_zip` writes, for every slice of every stack of an
answer, ``transforms/stack{S}_slice{K:03d}.tfm``: an ``AffineTransform_double_3_3`` in ITK's LPS
world frame,

    T_lps = F @ scanner_from_voxel @ inverse(atlas_from_voxel) @ F,   F = diag(-1, -1, 1, 1),

which maps a point of atlas space (LPS mm) to the point of the uploaded stack's physical space (LPS
mm, as the service placed the file: a NIfTI file by its sform whenever its code is above 0) where
that slice observed it: ITK's registration convention with the atlas as the fixed image, so
``sitk.Resample(stack_image, atlas_image, sitk.ReadTransform(path))`` puts that slice in atlas space,
``stack_image`` placed as the service placed it (SimpleITK places a NIfTI file whose qform and
sform differ by its qform where the sform's code is 2-4, and takes its voxel sizes from ``pixdim``:
set its origin, direction and spacing from ``scanner_from_voxel`` first). ``transforms/slice_transforms.txt`` lists every slice, one line
each: ``stack slice accepted expected_error_mm`` and the 12 numbers of the top 3 x 4 block of
``atlas_from_voxel`` (row-major). The layout and the ``.tfm`` text are those of a reconstruction
job's ``transforms.zip`` (docs/reconstruction.md), with the predicted poses.

``scanner_from_voxel`` is the stack's voxel -> scanner RAS map as the server read the file (each
``stacks[]`` object of the answer holds it), so DICOM series, whose voxel order the client need not
know, get their transforms too.

Example:
    >>> import numpy as np
    >>> atlas_from_voxel, scanner_from_voxel = np.diag([1.0, 1.0, 3.0, 1.0]), np.diag([1.0, 1.0, 3.0, 1.0])
    >>> atlas_from_voxel[:3, 3] = (5.0, 0.0, 0.0)                 # the slice lies 5 mm right of where it was acquired
    >>> t = stack_from_atlas_lps(atlas_from_voxel, scanner_from_voxel)
    >>> t[:3, 3].tolist()                                            # atlas LPS -> stack LPS: 5 mm along +L
    [5.0, 0.0, 0.0]
    >>> tfm_text(t).splitlines()[3]
    'Parameters: 1.0 0.0 0.0 0.0 1.0 0.0 0.0 0.0 1.0 5.0 0.0 0.0'
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from client.errors import UnusableInput
from client.files import write_whole

__all__ = ["stack_from_atlas_lps", "tfm_text", "transform_files", "write_transforms_zip"]

LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
"""RAS <-> LPS (its own inverse)."""
TFM_HEADER = "#Insight Transform File V1.0"


def stack_from_atlas_lps(atlas_from_voxel: ArrayLike, scanner_from_voxel: ArrayLike) -> NDArray[np.float64]:
    """The ``4 x 4`` LPS transform atlas -> the stack's physical space of one slice (see the module)."""
    scanner_from_atlas = np.asarray(scanner_from_voxel, np.float64) @ np.linalg.inv(np.asarray(atlas_from_voxel, np.float64))
    return LPS_FROM_RAS @ scanner_from_atlas @ LPS_FROM_RAS


def tfm_text(transform_lps: ArrayLike) -> str:
    """The ``.tfm`` text of one ``4 x 4`` world -> world affine given in LPS (centre 0)."""
    m = np.asarray(transform_lps, dtype=np.float64)
    params = " ".join(repr(float(v)) for v in list(m[:3, :3].ravel()) + list(m[:3, 3]))
    return (f"{TFM_HEADER}\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
            f"Parameters: {params}\nFixedParameters: 0 0 0\n")


def transform_files(answer: dict[str, Any]) -> dict[str, str]:
    """File name (in the zip) -> text, for every slice of a ``/v1/predict`` answer; :class:`UnusableInput`
    for an answer without ``scanner_from_voxel`` (a server older than that field)."""
    files: dict[str, str] = {}
    lines = ["# stack slice accepted expected_error_mm  atlas_from_voxel[0:3, 0:4] row-major "
             "(voxel index of the stack file -> atlas RAS mm)"]
    for stack in answer.get("stacks", []):
        if stack.get("scanner_from_voxel") is None:
            raise UnusableInput("transforms: the server's answer has no scanner_from_voxel per stack (a server "
                                "older than this client); update the server, or use a reconstruction job's transforms")
        s = int(stack["index"])
        for item in stack["slices"]:
            k, pose = int(item["index"]), np.asarray(item["atlas_from_voxel"], np.float64)
            files[f"transforms/stack{s}_slice{k:03d}.tfm"] = tfm_text(stack_from_atlas_lps(pose, stack["scanner_from_voxel"]))
            expected = item.get("expected_error_mm")
            matrix = " ".join(f"{v:.9g}" for v in pose[:3, :].ravel())
            lines.append(f"{s} {k} {int(bool(item.get('accepted')))} "
                         f"{'nan' if expected is None else f'{float(expected):.3f}'} {matrix}")
    files["transforms/slice_transforms.txt"] = "\n".join(lines) + "\n"
    return files


def write_transforms_zip(answer: dict[str, Any], target: Path) -> int:
    """Write :func:`transform_files` of ``answer`` as the zip ``target`` (whole or not at all); the
    number of slices."""
    files = transform_files(answer)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name in sorted(files):
            archive.writestr(name, files[name])
    write_whole(Path(target), buffer.getvalue())
    return len(files) - 1
