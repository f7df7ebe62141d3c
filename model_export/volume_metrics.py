"""A reconstructed volume against the atlas volume it was simulated from.

Example (a volume that is the truth itself, on the truth's own grid: NCC 1):
    >>> import numpy as np
    >>> from service.io.volume import Volume
    >>> img = np.random.default_rng(0).random((12, 12, 12)).astype(np.float32); aff = np.eye(4)
    >>> psnr, ncc = volume_psnr_ncc(Volume(img, aff), img, np.ones(img.shape, bool), aff)
    >>> round(ncc, 6), psnr > 60
    (1.0, True)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from service.geometry import sampling
from service.geometry.pose import apply
from service.io.volume import Volume


def volume_psnr_ncc(volume: Volume, img: NDArray, msk: NDArray, aff: NDArray,
                    frame: NDArray | None = None) -> tuple[float, float]:
    """PSNR (dB; peak: the truth's maximum in its mask) after a linear intensity fit, and NCC, at the
    reconstruction's voxels inside the truth's brain mask.

    Args:
        volume: the reconstruction (its affine: voxel -> atlas mm).
        img, msk, aff: the truth's image, brain mask and voxel -> atlas mm affine.
        frame: ``4 x 4`` truth atlas -> reconstruction frame; given, the volume is compared after
            undoing that common offset (the frame a reconstruction inherits from its starting poses).
    """
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in volume.array.shape], indexing="ij"), -1).reshape(-1, 3)
    pts = apply(volume.affine, ijk)
    ref = sampling.sample_points(img, aff, pts)
    inside = sampling.sample_points(msk, aff, pts) > 0.5
    values = volume.array.reshape(-1)
    if frame is not None:
        values = sampling.sample_points(volume.array, volume.affine, pts @ frame[:3, :3].T + frame[:3, 3])
    x = values[inside].astype(np.float64)
    y = ref[inside].astype(np.float64)
    a, b = np.polyfit(x, y, 1)
    psnr = 10 * np.log10(y.max() ** 2 / np.mean((a * x + b - y) ** 2))
    return float(psnr), float(np.corrcoef(x, y)[0, 1])
