"""What geometry an acquisition can have: a stack's voxel grid, and the files of a DICOM series.

**A grid** (:func:`grid_problem`). A file's header, a streamed slice's ``scanner_from_voxel`` and a
client's ``atlas_from_voxel`` all say how large a voxel is, and every later stage sizes its arrays
from that: the localiser resamples the whole field of view to its own pixels, a reconstruction's
grid spans the slices' positions. A header that claims 30 mm pixels makes a 320 x 320 slice 9.6 m
wide, and the localiser's grid of it 3,840 x 3,840 pixels a slice, however small the file. The
limits below are far outside what fetal MRI uses (0.4-2 mm pixels, 2-6 mm slices, a 200-450 mm field
of view) and far inside what costs the server its memory: a grid past them is not an acquisition,
and is answered as such before any stage runs.

**A DICOM series** (:func:`series_problem`). GDCM sorts a series' files along their normal and
reads them as one volume whatever their tags say: files without a position or at one position, a
file missing from the middle, orientations that differ from file to file, or pixel spacings of 0
all come back as a volume with an invented slice spacing or orientation (1 mm, the identity, the
first file's), and every pose of it is wrong. A series is taken only when every file has an
orientation (two unit vectors at right angles), the same one, a positive pixel spacing, the same
one, and a position, and the positions step evenly along the normal.

Example:
    >>> grid_problem(np.diag([1.1, 1.1, 3.0, 1.0]), (320, 320, 24)) is None
    True
    >>> grid_problem(np.diag([30.0, 30.0, 3.0, 1.0]), (320, 320, 24))
    'voxel size 30, 30, 3 mm: beyond 20 mm along an axis, which no MRI acquisition of a fetus uses'
    >>> grid_problem(np.diag([4.0, 4.0, 3.0, 1.0]), (320, 320, 24))
    'field of view 1280 x 1280 x 72 mm: beyond 1000 mm along an axis, wider than any MRI scanner'
    >>> tags = [((0.0, 0.0, 3.0 * k), (1, 0, 0, 0, 1, 0), (0.9, 0.9)) for k in range(5)]
    >>> series_problem(tags) is None
    True
    >>> series_problem(tags[:2] + tags[3:])
    'its slices are not evenly spaced (6 mm between slices 2 and 3, where the others lie 3 mm apart, counted along the stack): one is missing, or it holds more than one stack'
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.geometry.frames import voxel_spacing

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
    edges = voxel_spacing(affine)
    if not np.all(np.isfinite(edges)):
        return f"voxel size {_mm(edges)} mm: beyond any size a number can hold along an axis"
    if edges.min() < MIN_VOXEL_MM * (1 - _ROUNDING):
        return f"voxel size {_mm(edges)} mm: under {MIN_VOXEL_MM} mm along an axis, which no MRI acquisition has"
    if edges.max() > MAX_VOXEL_MM * (1 + _ROUNDING):
        return f"voxel size {_mm(edges)} mm: beyond {MAX_VOXEL_MM:.0f} mm along an axis, which no MRI acquisition " \
               "of a fetus uses"
    extent = edges * np.asarray(shape[:3], np.float64)
    if extent.max() > MAX_FIELD_OF_VIEW_MM * (1 + _ROUNDING):
        return (f"field of view {' x '.join(f'{e:.0f}' for e in extent)} mm: beyond {MAX_FIELD_OF_VIEW_MM:.0f} mm "
                "along an axis, wider than any MRI scanner")
    return None

Tags = tuple[Sequence[float] | None, Sequence[float] | None, Sequence[float] | None]
"""One file's ``(ImagePositionPatient, ImageOrientationPatient, PixelSpacing)``; None where absent."""

DIRECTION_TOLERANCE = 1e-3
"""How far an orientation's two vectors may be from unit length and right angles, and two files'
orientations from each other."""
SPACING_TOLERANCE = 0.05
"""How far (relative) a step between neighbouring slices may differ from the median step, and how
far (relative to a pixel) a stack's slices may drift within their plane over the stack."""
POSITION_ROUNDING_MM = 0.1
"""How far a slice's position may scatter within its plane about the stack's line: positions
written to a tenth of a millimetre (as some exports and anonymisers write them) lie up to 0.087 mm
off it."""
MIN_STEP_MM = 1e-3
"""Two files nearer each other than this along the normal are at one position."""


def _floats(values: Sequence[float] | None, n: int) -> np.ndarray | None:
    try:
        out = np.asarray([float(v) for v in values], np.float64) if values is not None else None
    except (TypeError, ValueError):
        return None
    return out if out is not None and out.shape == (n,) and np.all(np.isfinite(out)) else None


def series_problem(files: Sequence[Tags], what: str = "files") -> str | None:
    """Why the files (their tags, :data:`Tags`; ``what`` they are called in the answer: a series'
    files, a multi-frame file's frames) do not make one stack, or None. A stack's slices share one
    orientation and pixel spacing and lie evenly spaced along its normal, each straight behind the
    last: a slice shifted within its plane would make a sheared grid."""
    positions = [_floats(p, 3) for p, _, _ in files]
    orientations = [_floats(o, 6) for _, o, _ in files]
    spacings = [_floats(s, 2) for _, _, s in files]
    if (missing := sum(o is None for o in orientations)) or any(
            abs(np.linalg.norm(o[:3]) - 1) > DIRECTION_TOLERANCE or abs(np.linalg.norm(o[3:]) - 1) > DIRECTION_TOLERANCE
            or abs(o[:3] @ o[3:]) > DIRECTION_TOLERANCE for o in orientations):
        return f"ImageOrientationPatient is missing or not two unit vectors at right angles in " \
               f"{missing or 'some'} of its {len(files)} {what}"
    if np.abs(np.array(orientations) - orientations[0]).max() > DIRECTION_TOLERANCE:
        return f"its {what}' ImageOrientationPatient differ: they are not one stack"
    if (missing := sum(s is None or s.min() <= 0 for s in spacings)):
        return f"PixelSpacing is missing or not positive in {missing} of its {len(files)} {what}"
    if np.abs(np.array(spacings) - spacings[0]).max() > DIRECTION_TOLERANCE * spacings[0].max():
        return f"its {what}' PixelSpacing differ: they are not one stack"
    if (missing := sum(p is None for p in positions)):
        return f"ImagePositionPatient is missing in {missing} of its {len(files)} {what}"
    normal = np.cross(orientations[0][:3], orientations[0][3:])
    along = np.sort(np.array(positions) @ normal)
    if len(files) > 1 and (shear := in_plane_shear(np.array(positions), normal, float(spacings[0].min()))):
        return f"its {what} are shifted within their plane from one to the next ({shear}): a sheared grid, " \
               "not one stack"
    steps = np.diff(along)
    if len(steps) and steps.min() < MIN_STEP_MM:
        return f"two of its {what} lie at one position: it holds more than one stack, or one twice"
    if len(steps) and np.abs(steps - np.median(steps)).max() > SPACING_TOLERANCE * np.median(steps):
        odd = np.flatnonzero(np.abs(steps - np.median(steps)) > SPACING_TOLERANCE * np.median(steps))
        shown = ", ".join(f"{steps[k]:.3g} mm between slices {k + 1} and {k + 2}" for k in odd[:4]) \
            + (f" and {len(odd) - 4} more" if len(odd) > 4 else "")
        return f"its slices are not evenly spaced ({shown}, where the others lie {np.median(steps):.3g} mm apart, " \
               "counted along the stack): one is missing, or it holds more than one stack"
    return None


def in_plane_shear(positions: NDArray, normal: NDArray, pixel_mm: float) -> str | None:
    """What is wrong with slice ``positions [n, 3]`` (mm) within the plane of ``normal``, or None:
    a drift over the stack (the in-plane offsets' trend along the normal) of more than
    :data:`SPACING_TOLERANCE` of a pixel (a sheared grid), or a slice off that trend by more than
    that or :data:`POSITION_ROUNDING_MM`, whichever is more (rounding does not accumulate; a shear does).

    Example (24 slices 3.3 mm apart, positions rounded to 0.1 mm; then a drift of 0.1 mm a slice):
        >>> n = np.array([0.0, 0.07, 1.0]) / np.linalg.norm([0.0, 0.07, 1.0])
        >>> p = np.round(np.array([10.0, -20.0, 30.0]) + np.outer(np.arange(24) * 3.3, n), 1)
        >>> in_plane_shear(p, n, 1.1) is None, in_plane_shear(p + np.outer(np.arange(24) * 0.1, [1.0, 0, 0]), n, 1.1)
        (True, 'a drift of 2.3 mm over the stack')
    """
    t = positions @ normal
    offsets = positions - np.outer(t, normal)                                          # within the plane
    tc, rel = t - t.mean(), offsets - offsets.mean(axis=0)
    slope = (tc @ rel) / max(float(tc @ tc), 1e-12)
    drift = float(np.linalg.norm(slope) * (t.max() - t.min()))
    scatter = float(np.linalg.norm(rel - np.outer(tc, slope), axis=1).max())
    if drift > SPACING_TOLERANCE * pixel_mm:
        return f"a drift of {drift:.3g} mm over the stack"
    if scatter > max(SPACING_TOLERANCE * pixel_mm, POSITION_ROUNDING_MM):
        return f"a slice {scatter:.3g} mm off the others' line"
    return None


def stacking_problem(spacing: Sequence[float], n_slices: int) -> str | None:
    """Why a stack whose file says its slices run along its third axis (a DICOM series, a
    multi-frame file) cannot be used as one: slices closer together than its pixels, so that the
    axis of largest spacing, which API v1 takes as the slice axis, would be an in-plane one. None if
    it can.

    Example:
        >>> stacking_problem([1.2, 1.2, 1.0], 30)
        'its slices lie 1 mm apart, closer than its 1.2 mm pixels: the axis of largest spacing, the slice axis of API v1, would be an in-plane one; resample the stack to slices at least a pixel apart'
    """
    sp = np.asarray(spacing, np.float64)
    if n_slices < 2 or sp[2] >= sp[:2].max() * (1 - SPACING_TIE):
        return None
    return (f"its slices lie {sp[2]:.3g} mm apart, closer than its {sp[:2].max():.3g} mm pixels: the axis of largest "
            "spacing, the slice axis of API v1, would be an in-plane one; resample the stack to slices at least a "
            "pixel apart")


SPACING_TIE = 1e-3
"""Voxel spacings within this share of each other are one spacing (a header's rounding): the slice
axis, the axis of largest spacing, is then the last of those that share it."""


def slice_axis_problem(spacing: Sequence[float]) -> str | None:
    """Why a stack file that does not say which axis its slices run along (NIfTI, NRRD, MHA; by
    convention its third) cannot be cut into slices: its first two axes share the largest spacing
    and the third's is smaller (beyond :data:`SPACING_TIE`), so that its slices lie closer together
    than its pixels (slices that overlap, or a volume of nearly cubic voxels) and the axis of
    largest spacing, the slice axis of API v1, is an in-plane one. None if it can (a tie that holds
    the third axis leaves it the slice axis).

    Example:
        >>> slice_axis_problem([1.5, 1.5, 1.2])
        'its first two voxel axes share the largest spacing (1.5 mm) and its third lies 1.2 mm apart: its slices are closer together than its pixels, so the axis of largest spacing, the slice axis of API v1, is an in-plane one; resample the stack to slices at least a pixel apart'
        >>> slice_axis_problem([1.125, 1.125, 1.1])[:60]
        'its first two voxel axes share the largest spacing (1.12 mm)'
        >>> slice_axis_problem([1.2, 1.2, 3.0]), slice_axis_problem([1.0, 1.2, 1.2]), slice_axis_problem([1.0, 1.0, 0.9999])
        (None, None, None)
    """
    sp = np.asarray(spacing, np.float64)
    if abs(sp[0] - sp[1]) > SPACING_TIE * sp.max() or sp[2] >= sp[0] * (1 - SPACING_TIE):
        return None
    return (f"its first two voxel axes share the largest spacing ({sp[0]:.3g} mm) and its third lies "
            f"{sp[2]:.3g} mm apart: its slices are closer together than its pixels, so the axis of largest "
            "spacing, the slice axis of API v1, is an in-plane one; resample the stack to slices at least a pixel apart")


def stated_thickness(values: Sequence[object]) -> float | None:
    """The slice thickness the files or frames of one stack state (DICOM ``SliceThickness``), when
    every one states the same plausible value (within 1 %, :data:`MIN_VOXEL_MM` to
    :data:`MAX_VOXEL_MM`); else None (unknown: the slice spacing stands in for it).

    Example:
        >>> stated_thickness(["3.0", 3.0, "3.00"]), stated_thickness([3.0, None]), stated_thickness([3.0, 4.0])
        (3.0, None, None)
    """
    found = _floats(list(values), len(values)) if len(values) else None
    if found is None or found.min() < MIN_VOXEL_MM or found.max() > MAX_VOXEL_MM or np.ptp(found) > 0.01 * found.max():
        return None
    return float(np.median(found))


__all__ = ["MAX_FIELD_OF_VIEW_MM", "MAX_VOXEL_MM", "MIN_VOXEL_MM", "SPACING_TIE", "Tags", "grid_problem",
           "series_problem", "stacking_problem", "stated_thickness"]
