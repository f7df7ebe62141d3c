"""A PNG preview of a volume: three orthogonal planes of atlas space side by side.

Panels (left to right): sagittal (``x`` fixed), coronal (``y`` fixed), axial (``z`` fixed), each
through the middle voxel of the array and cut in atlas (RAS) space through the volume's affine,
whatever its grid's orientation: a job's volume keeps its atlas-frame and midline corrections in
its affine (its voxels are not resampled), so its array's own mid-planes may be tilted by them.
Superior is up in the first two panels and anterior up in the axial one, with the subject's right
on the right (neurological convention); pixels are squares of the finest voxel edge. Intensities
are windowed to the 1st-99th percentiles of the nonzero voxels. A strip below the panels names
their sides (``P``/``A`` under the sagittal panel, ``L``/``R`` under the others: the twin of a
left-right mirrored volume shows there) and carries a 10 mm scale bar.

Example:
    >>> import numpy as np
    >>> from service.io.volume import Volume
    >>> png = preview_png(Volume(np.random.default_rng(0).random((20, 24, 16)), np.eye(4)))
    >>> png[:8] == b"\\x89PNG\\r\\n\\x1a\\n"
    True
"""

from __future__ import annotations

import io
import itertools

import numpy as np
from numpy.typing import NDArray
from PIL import Image, ImageDraw
from scipy.ndimage import map_coordinates

from service.io.volume import Volume

GAP_PX = 12
"""Columns between two panels, a grey rule in the strip below them: the side letters of neighbouring
panels (``A`` and ``L``, ``R`` and ``L``) stand apart."""
LABEL_PX = 14
"""Height of the strip below the panels that names their sides and holds the scale bar."""
SCALE_MM = 10.0
SIDES = (("P", "A"), ("L", "R"), ("L", "R"))
"""What lies at each panel's left and right edge: the sagittal panel's columns run along atlas y, the
coronal and axial panels' along atlas x (neurological convention)."""


def window(array: NDArray, low: float = 1.0, high: float = 99.0) -> NDArray[np.uint8]:
    """Map intensities to ``0..255`` with the ``[low, high]`` percentiles of the nonzero values."""
    a = np.asarray(array, dtype=np.float32)
    vals = a[np.isfinite(a) & (a != 0)]
    if vals.size == 0:
        return np.zeros(a.shape, np.uint8)
    lo, hi = np.percentile(vals, [low, high])
    scale = 255.0 / (hi - lo) if hi > lo else 0.0
    out = np.clip((np.nan_to_num(a) - lo) * scale, 0, 255)
    return out.astype(np.uint8)


def atlas_planes(volume: Volume) -> list[NDArray[np.uint8]]:
    """The sagittal, coronal and axial planes of atlas space through the volume's middle voxel, over
    the volume's extent in atlas space, in square pixels of its finest voxel edge (linear
    interpolation; zero outside the volume). On a RAS-aligned grid of cubic voxels the pixels are
    the voxels of the array's own mid-planes."""
    windowed = window(volume.array)
    affine = np.asarray(volume.affine, dtype=np.float64)
    shape = np.array(windowed.shape)
    step = float(volume.spacing.min())
    corners = np.array(list(itertools.product(*[(-0.5, n - 0.5) for n in shape])))
    world = corners @ affine[:3, :3].T + affine[:3, 3]
    low, high = world.min(axis=0), world.max(axis=0)
    axes = [low[d] + (np.arange(max(1, round((high[d] - low[d]) / step))) + 0.5) * step for d in range(3)]
    centre = affine[:3, :3] @ (shape // 2) + affine[:3, 3]
    to_voxel = np.linalg.inv(affine)

    def plane(fixed: int, rows: int, columns: int) -> NDArray[np.uint8]:
        r, c = np.meshgrid(axes[rows][::-1], axes[columns], indexing="ij")     # rows from the top down
        points = np.empty(r.shape + (3,))
        points[..., fixed], points[..., rows], points[..., columns] = centre[fixed], r, c
        voxels = points @ to_voxel[:3, :3].T + to_voxel[:3, 3]
        values = map_coordinates(windowed, np.moveaxis(voxels, -1, 0), output=np.float32, order=1, mode="constant",
                                 cval=0.0)
        return np.clip(np.round(values), 0, 255).astype(np.uint8)

    return [plane(0, 2, 1), plane(1, 2, 0), plane(2, 1, 0)]


def preview_png(volume: Volume) -> bytes:
    """PNG bytes of the three orthogonal mid-planes of ``volume`` side by side (grayscale), with the
    strip that names their sides and a 10 mm scale bar below them."""
    panels = [Image.fromarray(np.ascontiguousarray(p)) for p in atlas_planes(volume)]
    height = max(p.height for p in panels)
    width = sum(p.width for p in panels) + GAP_PX * (len(panels) - 1)
    canvas = Image.new("L", (width, height + LABEL_PX), 0)
    draw = ImageDraw.Draw(canvas)
    x = 0
    for p, (left, right) in zip(panels, SIDES):
        canvas.paste(p, (x, (height - p.height) // 2))
        draw.text((x + 1, height + 1), left, fill=255)
        draw.text((x + p.width - 7, height + 1), right, fill=255)
        x += p.width + GAP_PX
        if x < width:
            draw.line([(x - GAP_PX // 2 - 1, height), (x - GAP_PX // 2 - 1, height + LABEL_PX - 1)], fill=96)
    bar = max(1, round(SCALE_MM / float(volume.spacing.min())))        # pixels are the finest voxel edge
    start = (panels[0].width - bar) // 2
    draw.line([(start, height + LABEL_PX // 2), (start + bar - 1, height + LABEL_PX // 2)], fill=255, width=2)
    buf = io.BytesIO()
    canvas.save(buf, format="PNG", optimize=True)
    return buf.getvalue()
