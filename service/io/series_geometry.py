"""Whether the files of one DICOM series make one stack: what GDCM does not check before it stacks them.

GDCM sorts a series' files along their normal and reads them as one volume whatever their tags say:
files without a position or at one position, a file missing from the middle, orientations that
differ from file to file, or pixel spacings of 0 all come back as a volume with an invented slice
spacing or orientation (1 mm, the identity, the first file's), and every pose of it is wrong. A
series is taken only when every file has an orientation (two unit vectors at right angles), the
same one, a positive pixel spacing, the same one, and a position, and the positions step evenly
along the normal.

Example:
    >>> tags = [((0.0, 0.0, 3.0 * k), (1, 0, 0, 0, 1, 0), (0.9, 0.9)) for k in range(5)]
    >>> series_problem(tags) is None
    True
    >>> series_problem(tags[:2] + tags[3:])
    'its slices are not evenly spaced (3, 6, 3 mm between neighbours): a file is missing, or it holds more than one stack'
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

Tags = tuple[Sequence[float] | None, Sequence[float] | None, Sequence[float] | None]
"""One file's ``(ImagePositionPatient, ImageOrientationPatient, PixelSpacing)``; None where absent."""

DIRECTION_TOLERANCE = 1e-3
"""How far an orientation's two vectors may be from unit length and right angles, and two files'
orientations from each other."""
SPACING_TOLERANCE = 0.05
"""How far (relative) a step between neighbouring slices may differ from the median step."""
MIN_STEP_MM = 1e-3
"""Two files nearer each other than this along the normal are at one position."""


def _floats(values: Sequence[float] | None, n: int) -> np.ndarray | None:
    try:
        out = np.asarray([float(v) for v in values], np.float64) if values is not None else None
    except (TypeError, ValueError):
        return None
    return out if out is not None and out.shape == (n,) and np.all(np.isfinite(out)) else None


def series_problem(files: Sequence[Tags]) -> str | None:
    """Why the files (their tags, :data:`Tags`) do not make one stack, or None."""
    positions = [_floats(p, 3) for p, _, _ in files]
    orientations = [_floats(o, 6) for _, o, _ in files]
    spacings = [_floats(s, 2) for _, _, s in files]
    if (missing := sum(o is None for o in orientations)) or any(
            abs(np.linalg.norm(o[:3]) - 1) > DIRECTION_TOLERANCE or abs(np.linalg.norm(o[3:]) - 1) > DIRECTION_TOLERANCE
            or abs(o[:3] @ o[3:]) > DIRECTION_TOLERANCE for o in orientations):
        return f"ImageOrientationPatient is missing or not two unit vectors at right angles in " \
               f"{missing or 'some'} of its {len(files)} files"
    if np.abs(np.array(orientations) - orientations[0]).max() > DIRECTION_TOLERANCE:
        return "its files' ImageOrientationPatient differ: they are not one stack"
    if (missing := sum(s is None or s.min() <= 0 for s in spacings)):
        return f"PixelSpacing is missing or not positive in {missing} of its {len(files)} files"
    if np.abs(np.array(spacings) - spacings[0]).max() > DIRECTION_TOLERANCE * spacings[0].max():
        return "its files' PixelSpacing differ: they are not one stack"
    if (missing := sum(p is None for p in positions)):
        return f"ImagePositionPatient is missing in {missing} of its {len(files)} files"
    normal = np.cross(orientations[0][:3], orientations[0][3:])
    along = np.sort(np.array(positions) @ normal)
    steps = np.diff(along)
    if len(steps) and steps.min() < MIN_STEP_MM:
        return "two of its files lie at one position: it holds more than one stack, or a file twice"
    if len(steps) and np.abs(steps - np.median(steps)).max() > SPACING_TOLERANCE * np.median(steps):
        shown = ", ".join(f"{s:.3g}" for s in steps[:8]) + (", ..." if len(steps) > 8 else "")
        return f"its slices are not evenly spaced ({shown} mm between neighbours): a file is missing, or it " \
               "holds more than one stack"
    return None


__all__ = ["Tags", "series_problem"]
