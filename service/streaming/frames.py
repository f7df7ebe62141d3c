"""Slices as a scanner sends them, one at a time, and the stack they add up to.

A streamed slice is a 2D array ``[n0, n1]`` with its ``scanner_from_voxel`` (RAS mm): voxel
``(i0, i1, 0, 1)`` -> scanner mm, the third column the slice normal times its thickness. The slices
of one stack share their in-plane axes and sit along one normal; :class:`StreamedStack` checks that
as they arrive and, once the stack ends (slices that never came blank), builds the
:class:`~service.io.volume.Volume` that ``/v1/predict`` would have read from a file: voxel
``(i0, i1, k)`` is pixel ``(i0, i1)`` of the slice of index ``k``, and the third column of its
affine is the step between neighbouring slices (the spacing, which may differ from the thickness
where slices have gaps or overlap).

Example:
    >>> import numpy as np
    >>> stack = StreamedStack("ax")
    >>> for k in (1, 0, 2):                                   # any order: interleaved, say
    ...     a = np.diag([1.0, 1.0, 3.0, 1.0]); a[:3, 3] = (0, 0, 3.5 * k)
    ...     stack.add(SliceFrame("ax", k, np.full((4, 5), k, np.float32), a))
    >>> vol, mask = stack.volume()
    >>> vol.array.shape, vol.spacing.round(2).tolist(), mask is None, stack.arrival_order()
    ((4, 5, 3), [1.0, 1.0, 3.5], True, (1, 0, 2))
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from service.core.errors import InvalidParameter
from service.geometry.frames import axes_cosine
from service.io.acquisition_geometry import POSITION_ROUNDING_MM, SPACING_TOLERANCE, grid_problem, in_plane_shear
from service.io.nifti_header import MAX_SHEAR_COS
from service.io.volume import Volume

AXIS_TOLERANCE = 1e-3
"""Largest relative difference between the in-plane axes of two slices of one stack."""
LINE_TOLERANCE_MM = 0.05
"""The least tolerance of a slice's place along the stack's normal (otherwise
:data:`~service.io.acquisition_geometry.SPACING_TOLERANCE` of the step between slices); within the
plane a slice may lie :data:`~service.io.acquisition_geometry.POSITION_ROUNDING_MM` or that share of
a pixel off the first slice's line, whichever is more: as ``/v1/predict`` allows a series."""


MAX_MISSING_SHARE = 0.5
"""The largest share of a stack's slices that may be missing when it ends: a scanner's dropped slice
costs its stack nothing but that slice, while a few slices sent again under a stack of their own
(a reacquisition) are not taken for a stack full of holes."""


class IncompleteStack(InvalidParameter):
    """A stack ended with too many of its slices missing (:meth:`StreamedStack.volume`)."""


class SlicesDropped(InvalidParameter):
    """A stack did not end: the slices ``indices`` lay off its even spacing and were dropped from it,
    to be sent again (:meth:`~service.streaming.session.StreamSession.end_stack`)."""

    def __init__(self, detail: str, indices: list[int]) -> None:
        super().__init__(detail)
        self.indices = list(indices)


@dataclass
class SliceFrame:
    """One slice as sent: its stack's name, its index along the stack normal, pixels and geometry.

    Attributes:
        stack: the client's name of the stack.
        index: position of the slice in its stack along the normal, 0-based.
        pixels: ``[n0, n1]`` intensities.
        scanner_from_voxel: ``4 x 4``: voxel ``(i0, i1, 0, 1)`` -> scanner RAS mm; third column the
            normal times the slice thickness.
        mask: ``[n0, n1]`` brain mask (None: the service localises the brain).
        acquisition_index: the slice's place in its stack's acquisition, when the client says it
            (otherwise the order the slices arrive in is the acquisition order).
    """

    stack: str
    index: int
    pixels: NDArray
    scanner_from_voxel: NDArray[np.float64]
    mask: NDArray[np.bool_] | None = None
    acquisition_index: int | None = None

    @property
    def thickness_mm(self) -> float:
        return float(np.linalg.norm(self.scanner_from_voxel[:3, 2]))


def check_frame(frame: SliceFrame, max_pixels: int) -> None:
    """Raise :class:`InvalidParameter` naming the field when ``frame`` cannot be a slice."""
    px = np.asarray(frame.pixels)
    if px.ndim != 2 or min(px.shape) < 2:
        raise InvalidParameter(f"slice.shape: a slice is a 2D array of at least 2 x 2 pixels, not {list(px.shape)}")
    if px.size > max_pixels:
        raise InvalidParameter(f"slice.shape: {px.shape[0]} x {px.shape[1]} pixels is over this server's limit of "
                               f"{max_pixels} pixels per slice")
    if not np.all(np.isfinite(px)):
        raise InvalidParameter("slice: the pixels hold NaN or infinite values")
    if frame.index < 0:
        raise InvalidParameter(f"slice.index: {frame.index} is negative (indices start at 0)")
    a = np.asarray(frame.scanner_from_voxel, dtype=np.float64)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)) or not np.allclose(a[3], [0, 0, 0, 1]):
        raise InvalidParameter("slice.scanner_from_voxel: a 4 x 4 affine with last row 0, 0, 0, 1 is required")
    lengths = np.linalg.norm(a[:3, :3], axis=0)
    if lengths.min() <= 1e-6 or abs(np.linalg.det(a[:3, :3] / lengths)) < 0.5:
        raise InvalidParameter("slice.scanner_from_voxel: its columns (pixel axes and normal x thickness) must be "
                               "nonzero and not parallel")
    if (cos := float(axes_cosine(a[:3, :3]))) > MAX_SHEAR_COS:                # as a stack file's grid
        raise InvalidParameter(f"slice.scanner_from_voxel: its columns are sheared ({np.degrees(np.arccos(cos)):.2f} "
                               "deg apart, not 90); send the pixel axes and the normal at right angles")
    if (problem := grid_problem(a, px.shape + (1,))) is not None:
        raise InvalidParameter(f"slice.scanner_from_voxel: {problem}")
    if frame.mask is not None and np.asarray(frame.mask).shape != px.shape:
        raise InvalidParameter(f"slice.mask: shape {list(np.asarray(frame.mask).shape)} differs from the slice's "
                               f"{list(px.shape)}")


def along_normal(frame: SliceFrame, first: SliceFrame, normal: NDArray[np.float64]) -> float:
    """How far ``frame``'s origin lies from ``first``'s along the stack's unit ``normal`` (mm)."""
    return float((frame.scanner_from_voxel[:3, 3] - first.scanner_from_voxel[:3, 3]) @ normal)


@dataclass
class StreamedStack:
    """The slices of one stack received so far, checked to form one stack (see the module)."""

    name: str
    frames: dict[int, SliceFrame] = field(default_factory=dict)
    arrivals: list[int] = field(default_factory=list)
    floor: float = 0.0
    """The air floor its first slice decided (:func:`~service.io.volume.air_floor`): every slice of the
    stack loses it, so that its slices keep one offset, as a file's do."""

    def add(self, frame: SliceFrame) -> None:
        """Keep ``frame`` (:class:`InvalidParameter`, the stack unchanged, when it does not fit)."""
        if frame.index in self.frames:
            raise InvalidParameter(f"slice.index: stack {self.name!r} already has a slice {frame.index}")
        if self.frames:
            self._check_fits(frame, self.frames[self.arrivals[0]])
        self.frames[frame.index] = frame
        self.arrivals.append(frame.index)

    def _check_fits(self, frame: SliceFrame, first: SliceFrame) -> None:
        if np.shape(frame.pixels) != np.shape(first.pixels):
            raise InvalidParameter(f"slice.shape: {list(np.shape(frame.pixels))} differs from the "
                                   f"{list(np.shape(first.pixels))} of stack {self.name!r}'s first slice")
        a, b = frame.scanner_from_voxel, first.scanner_from_voxel
        if np.abs(a[:3, :3] - b[:3, :3]).max() > AXIS_TOLERANCE * np.abs(b[:3, :3]).max():
            raise InvalidParameter(f"slice.scanner_from_voxel: its axes differ from those of stack {self.name!r}'s "
                                   "first slice (a stack's slices are parallel, of one pixel grid)")
        normal = b[:3, 2] / np.linalg.norm(b[:3, 2])
        offset = a[:3, 3] - b[:3, 3]
        pixel_mm = float(np.linalg.norm(b[:3, :2], axis=0).min())
        if np.linalg.norm(offset - normal * (offset @ normal)) > max(SPACING_TOLERANCE * pixel_mm, POSITION_ROUNDING_MM):
            raise InvalidParameter(f"slice.scanner_from_voxel: the slice is shifted in plane from stack {self.name!r}'s "
                                   "other slices (they must lie along one normal)")
        if (frame.mask is None) != (first.mask is None):
            raise InvalidParameter(f"slice.mask: either every slice of stack {self.name!r} comes with a mask or none does")
        self._check_place(frame, first, normal)

    def _check_place(self, frame: SliceFrame, first: SliceFrame, normal: NDArray[np.float64]) -> None:
        """A slice's index is its place along the normal. It may not sit where a received slice of
        another index does; once the received slices agree on a line (:meth:`agreed_line`), its
        origin lies where that line puts the slice of its index, within :meth:`place_tolerance_mm`,
        widened as far as the line is extrapolated. Until they agree (fewer than three slices on one
        line, or not most of them, and two slices a step other than their thickness apart) a slice is
        kept wherever it lies: one misplaced slice among the first two must not make the line that
        refuses every correct slice after it; it lies off the line the later ones draw, and the
        stack's end drops it to be sent again (:meth:`off_line`)."""
        along = along_normal(frame, first, normal)
        for k, other in self.frames.items():
            if abs(along - along_normal(other, first, normal)) < LINE_TOLERANCE_MM:
                raise InvalidParameter(f"slice.scanner_from_voxel: slice {frame.index} sits where slice {k} of stack "
                                       f"{self.name!r} does (each index is its own place along the normal)")
        agreed = self.agreed_line(first, normal)
        if agreed is None:
            return
        start, step, on = agreed
        expected = start + step * frame.index
        lo, hi = min(on), max(on)
        reach = max(lo - frame.index, frame.index - hi, 0) / (hi - lo)        # the step's rounding, extrapolated
        if abs(along - expected) > self.place_tolerance_mm(step) * (1.0 + 2.0 * reach):
            raise InvalidParameter(f"slice.index: slice {frame.index} of stack {self.name!r} lies {along:.2f} mm along the "
                                   f"normal from slice {first.index}, where the stack's slices put index {frame.index} "
                                   f"at {expected:.2f} mm (a slice's index is its place along the normal, the slices "
                                   "evenly spaced)")

    def agreed_line(self, first: SliceFrame, normal: NDArray[np.float64]) -> tuple[float, float, list[int]] | None:
        """``(start, step, on)``: the received slices' robust line (:meth:`line`) and the slices on it,
        where at least three slices and most of them lie on it, or two whose step is the slices'
        thickness (the third column's length: contiguous slices); None otherwise."""
        if len(self.frames) < 2:
            return None
        start, step, off = self.line_and_misfits(first, normal)
        if len(self.frames) == 2:
            agree = abs(abs(step) - first.thickness_mm) <= self.place_tolerance_mm(step)
            return (start, step, sorted(self.frames)) if agree else None
        on = [k for k, miss in off.items() if miss <= self.place_tolerance_mm(step)]
        return (start, step, on) if len(on) >= 3 and 2 * len(on) > len(self.frames) else None

    def line(self, first: SliceFrame, normal: NDArray[np.float64]) -> tuple[float, float]:
        """``(start, step)``: where the received slices put index 0 and the step between neighbours,
        mm along ``normal`` from ``first``: the median step over every pair of slices and the median of
        what each slice then says of index 0 (one slice off the line moves neither)."""
        idx = np.array(sorted(self.frames), dtype=np.float64)
        along = np.array([along_normal(self.frames[int(k)], first, normal) for k in idx])
        i, j = np.triu_indices(len(idx), 1)
        step = float(np.median((along[j] - along[i]) / (idx[j] - idx[i])))
        return float(np.median(along - step * idx)), step

    def line_and_misfits(self, first: SliceFrame, normal: NDArray[np.float64]) -> tuple[float, float, dict[int, float]]:
        """:meth:`line` and each received slice's distance from it along ``normal`` (mm)."""
        start, step = self.line(first, normal)
        return start, step, {k: abs(along_normal(f, first, normal) - start - step * k) for k, f in self.frames.items()}

    @staticmethod
    def place_tolerance_mm(step: float) -> float:
        """How far a slice may lie from its even place: :data:`SPACING_TOLERANCE` of the step (as
        ``/v1/predict`` allows a series' steps to differ), at least :data:`LINE_TOLERANCE_MM`."""
        return max(LINE_TOLERANCE_MM, SPACING_TOLERANCE * abs(step))

    def off_line(self) -> list[int]:
        """The received slices farther from the stack's robust line (:meth:`line`) than
        :meth:`place_tolerance_mm` (none with fewer than three slices)."""
        if len(self.frames) < 3:
            return []
        first = self.frames[self.arrivals[0]]
        normal = first.scanner_from_voxel[:3, 2] / np.linalg.norm(first.scanner_from_voxel[:3, 2])
        _, step, off = self.line_and_misfits(first, normal)
        return sorted(k for k, miss in off.items() if miss > self.place_tolerance_mm(step))

    def remove(self, index: int) -> None:
        """Forget the slice ``index`` (one the service could not take after all)."""
        self.frames.pop(index, None)
        self.arrivals.remove(index)

    def __len__(self) -> int:
        return len(self.frames)

    def arrival_order(self) -> tuple[int, ...]:
        """The slice indices in the order they were acquired: as the client numbered them
        (``acquisition_index``) where every slice has one, else as they arrived."""
        given = [self.frames[k].acquisition_index for k in self.arrivals]
        if all(g is not None for g in given):
            return tuple(k for _, k in sorted(zip(given, self.arrivals)))
        return tuple(self.arrivals)

    def missing(self) -> list[int]:
        """The indices below the largest received one that have not arrived."""
        return sorted(set(range(max(self.frames) + 1)) - set(self.frames)) if self.frames else []

    def step_mm(self) -> float | None:
        """The distance between neighbouring slices, from the two received slices furthest apart in
        index (None with fewer than two)."""
        if len(self.frames) < 2:
            return None
        lo, hi = min(self.frames), max(self.frames)
        shift = self.frames[hi].scanner_from_voxel[:3, 3] - self.frames[lo].scanner_from_voxel[:3, 3]
        return float(np.linalg.norm(shift)) / (hi - lo)

    def volume(self, checked: bool = False) -> tuple[Volume, Volume | None]:
        """The stack as a volume (and its mask volume, when the slices came with masks): voxel
        ``(i0, i1, k)`` is slice ``k``. A slice that has not arrived (:meth:`missing`) is blank,
        with no brain in its mask, at its place on the stack's line: the stack is judged by what
        came and the caller names what did not. :class:`IncompleteStack` when more than
        :data:`MAX_MISSING_SHARE` of the slices, or all but one, are missing;
        :class:`InvalidParameter` when the slices are unevenly spaced (``checked``: the caller has
        found no slice off the even spacing, :meth:`off_line`, already).

        Example:
            >>> stack = StreamedStack("ax")
            >>> for k in (1, 2, 4):
            ...     a = np.diag([1.0, 1.0, 3.0, 1.0]); a[:3, 3] = (0, 0, 3.5 * k)
            ...     stack.add(SliceFrame("ax", k, np.ones((4, 5), np.float32), a))
            >>> vol, _ = stack.volume()
            >>> stack.missing(), vol.array.shape, vol.array[0, 0].tolist(), float(vol.affine[2, 3])
            ([0, 3], (4, 5, 5), [0.0, 1.0, 1.0, 0.0, 1.0], 0.0)
        """
        if not self.frames:
            raise InvalidParameter(f"end_stack.stack: stack {self.name!r} has no slices")
        gaps = self.missing()
        n = len(self.frames) + len(gaps)
        if gaps and (len(self.frames) < 2 or len(gaps) > MAX_MISSING_SHARE * n):
            raise IncompleteStack(f"end_stack.stack: stack {self.name!r} lacks the slices {gaps[:10]} (indices 0.."
                                  f"{n - 1} are expected; a stack ends with at most {MAX_MISSING_SHARE:.0%} of its "
                                  "slices missing, and at least two received)")
        if not checked and self.off_line():
            raise InvalidParameter(f"end_stack.stack: the slices of stack {self.name!r} are not evenly spaced along "
                                   "their normal")
        first = self.frames[self.arrivals[0]].scanner_from_voxel
        if len(self.frames) > 1 and (shear := in_plane_shear(
                np.stack([f.scanner_from_voxel[:3, 3] for f in self.frames.values()]),
                first[:3, 2] / np.linalg.norm(first[:3, 2]), float(np.linalg.norm(first[:3, :2], axis=0).min()))):
            raise InvalidParameter(f"end_stack.stack: the slices of stack {self.name!r} are shifted within their "
                                   f"plane ({shear}): a sheared grid, not one stack")
        lo, hi = min(self.frames), max(self.frames)
        affine = np.array(self.frames[lo].scanner_from_voxel, dtype=np.float64)
        if hi > lo:
            affine[:3, 2] = (self.frames[hi].scanner_from_voxel[:3, 3] - affine[:3, 3]) / (hi - lo)
        if np.linalg.norm(affine[:3, 2]) < 1e-3:
            raise InvalidParameter(f"end_stack.stack: the slices of stack {self.name!r} all sit at one position")
        affine[:3, 3] -= lo * affine[:3, 2]                        # where slice 0 sits, received or not
        blank = np.zeros(np.shape(self.frames[lo].pixels), np.float32)
        image = np.stack([np.asarray(self.frames[k].pixels, np.float32) if k in self.frames else blank
                          for k in range(n)], axis=-1)
        mask = None
        if self.frames[lo].mask is not None:
            mask = Volume(np.stack([np.asarray(self.frames[k].mask, bool) if k in self.frames else blank > 0
                                    for k in range(n)], axis=-1), affine, slice_axis=2)
        return Volume(image, affine, slice_axis=2), mask
