"""N4 bias-field correction, fitted small and applied at full resolution.

The field is smooth, so it is fitted on an image shrunk to pixels of about 8 mm (in-plane by 4 at
least, but never to fewer than 4 samples along an axis) and restricted to the region around the brain (the mask's
bounding box plus a margin), on two fitting levels (a third, with twice the control points, fits a
field finer than the brain's extent needs). The fit is N4 in numpy
(:func:`~service.preprocess.n4.n4_log_field`: ITK's algorithm and ITK's field, without ITK's fixed
cost per iteration, which dominates on a fit image of a few thousand voxels) on samples on the
lattice of the whole stack's centred samples, over the region and a sample's spacing around it
(:func:`centred_samples`: a file that stores an axis the other way gets the same samples, a region
a voxel larger the same but where a sample enters); SimpleITK thresholds the fit mask (Otsu); the fitted log field is
interpolated linearly onto the full-resolution grid of the region (:func:`upsample_linear`: three
small matrix products), where it is divided out. Outside the region the image is left as it is (it
is masked out later anyway).

Example:
    >>> import numpy as np
    >>> from service.io.volume import Volume
    >>> x = np.linspace(-1, 1, 48)
    >>> field = np.exp(0.3 * x)[:, None, None] * np.ones((48, 48, 6))
    >>> vol = Volume((100 * field).astype(np.float32), np.diag([1.0, 1.0, 3.0, 1.0]))
    >>> out = n4_correct(vol, np.ones(vol.array.shape, bool))
    >>> bool(out.std() < vol.array.std())
    True
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from service.geometry.frames import voxels_covering
from service.geometry.sampling import linear_operator
from service.io.volume import Volume
from service.preprocess.n4 import n4_log_field
from service.preprocess.stack import mask_box

MARGIN_MM = 20.0
FIT_SPACING_MM = 8.0
ITERATIONS = 50
"""N4's iterations per fitting level at most; a level stops earlier once the field converges."""
LEVELS = 2


def n4_correct(volume: Volume, mask: NDArray | None = None, *, shrink: int = 4, iterations: int = ITERATIONS,
               levels: int = LEVELS, margin_mm: float = MARGIN_MM,
               fit_spacing_mm: float = FIT_SPACING_MM) -> NDArray[np.float32]:
    """Bias-corrected copy of ``volume.array``; the fit uses ``mask`` (dilated by its ROI) if given.

    Args:
        volume: the stack.
        mask: brain mask on the stack's grid (the fit region is its bounding box plus ``margin_mm``).
        shrink: in-plane shrink factor of the fit (at least).
        iterations, levels: N4's iterations per fitting level (it stops earlier when it converges), and the levels.
        margin_mm: margin of the fit region around the mask.
        fit_spacing_mm: the fit's in-plane pixel size is at least this: fine in-plane pixels are
            shrunk further (a 0.55 mm stack by 15, not 4).
    """
    arr = np.asarray(volume.array, dtype=np.float32)
    box = None if mask is None else mask_box(np.asarray(mask, bool), voxels_covering(margin_mm, volume.spacing))
    box = box or tuple(slice(0, n) for n in arr.shape)
    region = volume.region(box)
    # The fit works on the voxel grid alone (the field lives on the index domain), on samples on the
    # lattice of the whole stack's centred samples: the same samples whichever way the file stores its
    # axes (a shrink from the first voxel, as ITK's, samples a stack stored last to first elsewhere and
    # moved its poses by about an MC draw's spread) and whatever the region's exact extent, and no
    # physical position to round.
    sp = np.asarray(region.spacing, np.float64)
    target = max(shrink * min(sp), fit_spacing_mm)
    factors = [max(1, int(round(target / s))) for s in sp]                    # keep thick-slice axis
    factors = [min(f, max(1, (b.stop - b.start) // 4)) for f, b in zip(factors, box)]
    # the region and a sample's spacing around it (where the stack has it): samples cover the region
    reach = tuple(slice(max(b.start - f, 0), min(b.stop + f, n)) for b, f, n in zip(box, factors, arr.shape))
    through = [centred_first(n, f) - r.start for n, f, r in zip(arr.shape, factors, reach)]   # the whole stack's
    small, at = centred_samples(np.maximum(arr[reach], 0.0), factors, through)
    at = [a[b.start - r.start:b.stop - r.start] for a, b, r in zip(at, box, reach)]   # the region's voxels
    import SimpleITK as sitk      # here: a training host prepares stacks without N4 and has no SimpleITK

    small_image = sitk.GetImageFromArray(np.ascontiguousarray((small / otsu_unit(small)).transpose(2, 1, 0)))
    fit_mask = sitk.GetArrayFromImage(sitk.OtsuThreshold(small_image, 0, 1, 200)).transpose(2, 1, 0) > 0
    if fit_mask.sum() < 10:
        fit_mask = small > 0
    field = n4_log_field(small, fit_mask, (iterations,) * levels)
    log_field = upsample_linear(field, at)
    out = arr.copy()
    out[box] = arr[box] / np.exp(log_field)
    return out


def otsu_unit(values: NDArray) -> np.float32:
    """The unit the fit image is divided by before ITK's Otsu threshold: its largest value (1 where
    it holds none above 0). ITK's histogram does not tell apart values that are small in absolute
    terms, so a stack stored in very small units (brain values of 1e-9, say) would get another fit
    mask than the same stack in ordinary units; divided by it, every stack is thresholded on one scale.

    Example:
        >>> bool(otsu_unit(np.array([0.0, 2e-9, 5e-9], np.float32)) == np.float32(5e-9)), float(otsu_unit(np.zeros(3)))
        (True, 1.0)
    """
    peak = np.float32(np.max(values)) if np.size(values) else np.float32(0.0)
    return peak if np.isfinite(peak) and peak > 0 else np.float32(1.0)


def centred_first(n: int, factor: int) -> float:
    """Where the first of ``n // factor`` samples ``factor`` voxels apart, centred on an axis of ``n``
    voxels, lies (an index, a voxel or halfway between two).

    Example:
        >>> centred_first(7, 2), centred_first(32, 4)
        (1.0, 1.5)
    """
    return (n - 1) / 2.0 - factor * (max(1, n // factor) - 1) / 2.0


def centred_samples(values: NDArray, factors: list[int], through: list[float] | None = None,
                    ) -> tuple[NDArray[np.float32], list[NDArray[np.float64]]]:
    """``values`` shrunk by ``factors``: samples ``factor`` voxels apart on a lattice through
    ``through`` (per axis, an index, a voxel or halfway between two), every one that lies in
    ``values`` (default: ``n // factor`` samples centred on the axis's middle); and, per axis,
    where each of ``values``' voxels lies in the shrunk grid's continuous index. A sample halfway
    between two voxels is their mean.
    Samples, not block means, as ITK's shrink: N4 sharpens the histogram of the fit image, and means
    of blocks that straddle tissues fill in the peaks it sharpens.

    The lattice of the whole stack's centred samples (:func:`n4_correct`, on the fit region and a
    sample's spacing around it) is the same whichever way the file stores its axes (reversing an
    axis reverses its samples), and the same for a fit region a voxel larger or smaller: only a
    sample that enters or leaves changes (samples centred on the region moved by half a voxel when
    the mask grew by one voxel at its edge, and the field and the poses with it).

    Example (7 voxels every 2: samples at voxels 1, 3 and 5; through voxel 4: 0, 2, 4 and 6):
        >>> small, at = centred_samples(np.arange(7.0)[:, None, None], [2, 1, 1])
        >>> small[:, 0, 0].tolist(), at[0][[0, 6]].tolist()
        ([1.0, 3.0, 5.0], [-0.5, 2.5])
        >>> centred_samples(np.arange(7.0)[:, None, None], [2, 1, 1], [4.0, 0.0, 0.0])[0][:, 0, 0].tolist()
        [0.0, 2.0, 4.0, 6.0]
    """
    out = np.asarray(values, np.float64)
    at = []
    for axis, f in enumerate(factors):
        n = out.shape[axis]
        anchor = centred_first(n, f) if through is None else float(through[axis])
        first = float(np.mod(anchor, f))                    # the first sample's place: a voxel or halfway
        m = int(np.floor((n - 1 - first) / f)) + 1          # every lattice point inside
        if m < 1:                                           # none inside: one sample, the middle's
            first, m = (n - 1) / 2.0, 1
        low = int(np.floor(first))
        moved = np.moveaxis(out, axis, 0)
        picked = moved[low:low + f * (m - 1) + 1:f]
        if first != low:
            picked = 0.5 * picked + 0.5 * moved[low + 1:low + f * (m - 1) + 2:f]
        out = np.moveaxis(picked, 0, axis)
        at.append((np.arange(n) - first) / f)
    return out.astype(np.float32), at


def upsample_linear(values: NDArray, at: list[NDArray]) -> NDArray[np.float32]:
    """``values [X, Y, Z]`` interpolated trilinearly at the continuous indices ``at`` (one array per
    axis; the result is their outer grid), as one 1D interpolation per axis
    (:func:`~service.geometry.sampling.linear_operator`). Within the grid this is ITK's linear
    interpolator; beyond it, the value at the nearest point of the grid (continuous, where ITK's
    nearest-neighbour extrapolation jumps to the nearest voxel in every axis).

    Example (a ramp along x, sampled between its pixels and beyond its end):
        >>> v = np.arange(3.0)[:, None, None] * np.ones((3, 1, 1))
        >>> upsample_linear(v, [np.array([0.5, 1.25, 4.0]), np.zeros(1), np.zeros(1)])[:, 0, 0].tolist()
        [0.5, 1.25, 2.0]
    """
    out = np.asarray(values, np.float64)
    for c in at:                          # axis 0 contracted, the new axis last: after three, the order is back
        out = np.tensordot(out, linear_operator(c, len(out), np.float64).toarray(), (0, 1))
    return out.astype(np.float32)
