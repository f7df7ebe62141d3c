"""A PNG preview of a volume: three orthogonal mid-planes side by side.

Panels (left to right): sagittal (``i`` fixed), coronal (``j`` fixed), axial (``k`` fixed), each
through the middle of the array. For a RAS-aligned grid (what :func:`~service.reconstruction.pipeline.reconstruct`
writes) superior is up in the first two panels and anterior up in the axial one, with the
subject's right on the right (neurological convention). Intensities are windowed to the 1st-99th
percentiles of the nonzero voxels; anisotropic voxels are resized to their physical aspect.

Example:
    >>> import numpy as np
    >>> from service.io.volume import Volume
    >>> png = preview_png(Volume(np.random.default_rng(0).random((20, 24, 16)), np.eye(4)))
    >>> png[:8] == b"\\x89PNG\\r\\n\\x1a\\n"
    True
"""

from __future__ import annotations

import io

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from service.io.volume import Volume

GAP_PX = 2


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


def _panel(plane: NDArray[np.uint8], row_mm: float, col_mm: float) -> Image.Image:
    img = Image.fromarray(np.ascontiguousarray(plane))
    if abs(row_mm - col_mm) > 1e-3 * max(row_mm, col_mm):
        base = min(row_mm, col_mm)
        size = (max(1, round(plane.shape[1] * col_mm / base)), max(1, round(plane.shape[0] * row_mm / base)))
        img = img.resize(size, Image.BILINEAR)
    return img


def mid_planes(volume: Volume) -> list[Image.Image]:
    """The three mid-plane panels (sagittal, coronal, axial) as 8-bit images."""
    vol = window(volume.array)
    sp = volume.spacing
    ci, cj, ck = (s // 2 for s in vol.shape)
    sag = vol[ci, :, :].T[::-1]                  # rows: k (superior up), columns: j (anterior right)
    cor = vol[:, cj, :].T[::-1]                  # rows: k, columns: i
    axi = vol[:, :, ck].T[::-1]                  # rows: j (anterior up), columns: i
    return [_panel(sag, sp[2], sp[1]), _panel(cor, sp[2], sp[0]), _panel(axi, sp[1], sp[0])]


def preview_png(volume: Volume) -> bytes:
    """PNG bytes of the three orthogonal mid-planes of ``volume`` side by side (grayscale)."""
    panels = mid_planes(volume)
    height = max(p.height for p in panels)
    width = sum(p.width for p in panels) + GAP_PX * (len(panels) - 1)
    canvas = Image.new("L", (width, height), 0)
    x = 0
    for p in panels:
        canvas.paste(p, (x, (height - p.height) // 2))
        x += p.width + GAP_PX
    buf = io.BytesIO()
    canvas.save(buf, format="PNG", optimize=True)
    return buf.getvalue()
