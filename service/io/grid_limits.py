"""What a stack's voxel grid may be: the geometry an MRI scanner can write for a pregnant abdomen.

A file's header, a streamed slice's ``scanner_from_voxel`` and a client's ``atlas_from_voxel`` all
say how large a voxel is, and every later stage sizes its arrays from that: the localiser resamples
the whole field of view to its own pixels, a reconstruction's grid spans the slices' positions. A
header that claims 30 mm pixels makes a 320 x 320 slice 9.6 m wide, and the localiser's grid of it
3,840 x 3,840 pixels a slice, however small the file. The limits below are far outside what fetal
MRI uses (0.4-2 mm pixels, 2-6 mm slices, a 200-450 mm field of view) and far inside what costs
the server its memory: a grid past them is not an acquisition, and is answered as such before any
stage runs.

Example:
    >>> grid_problem(np.diag([1.1, 1.1, 3.0, 1.0]), (320, 320, 24)) is None
    True
    >>> grid_problem(np.diag([30.0, 30.0, 3.0, 1.0]), (320, 320, 24))
    'voxel size 30, 30, 3 mm: beyond 20 mm along an axis, which no MRI acquisition of a fetus uses'
    >>> grid_problem(np.diag([4.0, 4.0, 3.0, 1.0]), (320, 320, 24))
    'field of view 1280 x 1280 x 72 mm: beyond 1000 mm along an axis, wider than any MRI scanner'
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

MIN_VOXEL_MM = 0.05
"""Smallest voxel edge (mm) accepted (fetal MRI: 0.3 mm pixels at the finest)."""
MAX_VOXEL_MM = 20.0
"""Largest voxel edge (mm) accepted (fetal MRI: slices of up to 6-8 mm, with gaps)."""
MAX_FIELD_OF_VIEW_MM = 1000.0
"""Largest extent of a grid along one of its axes (mm): wider than any MRI scanner's bore."""
_ROUNDING = 1e-9
"""A limit holds to this relative part (a turned affine's column lengths are not exact)."""


def _mm(values: ArrayLike) -> str:
    return ", ".join(f"{v:.3g}" for v in np.asarray(values, np.float64))


def grid_problem(affine: ArrayLike, shape: tuple[int, ...]) -> str | None:
    """Why the grid of ``shape`` (voxel -> world ``affine``, 4 x 4) cannot be an acquisition, or None.

    The voxel edges are the lengths of the affine's first three columns; the field of view along an
    axis is the voxel count times that edge.
    """
    a = np.asarray(affine, dtype=np.float64)
    edges = np.linalg.norm(a[:3, :3], axis=0)
    if not np.all(np.isfinite(edges)) or edges.min() < MIN_VOXEL_MM * (1 - _ROUNDING):
        return f"voxel size {_mm(edges)} mm: under {MIN_VOXEL_MM} mm along an axis, which no MRI acquisition has"
    if edges.max() > MAX_VOXEL_MM * (1 + _ROUNDING):
        return f"voxel size {_mm(edges)} mm: beyond {MAX_VOXEL_MM:.0f} mm along an axis, which no MRI acquisition " \
               "of a fetus uses"
    extent = edges * np.asarray(shape[:3], np.float64)
    if extent.max() > MAX_FIELD_OF_VIEW_MM * (1 + _ROUNDING):
        return (f"field of view {' x '.join(f'{e:.0f}' for e in extent)} mm: beyond {MAX_FIELD_OF_VIEW_MM:.0f} mm "
                "along an axis, wider than any MRI scanner")
    return None


__all__ = ["MAX_FIELD_OF_VIEW_MM", "MAX_VOXEL_MM", "MIN_VOXEL_MM", "grid_problem"]
