"""Each slice's head ellipse: every plane cuts a skull in about an ellipse, and what a slice's region
holds beyond its ellipse is not head.

:func:`trim_to_head_ellipses` finds, per slice of a brain's component on the localiser's grid, the
ellipse its outline follows (RANSAC over conics through five outline pixels, a fixed seed) and cuts
what lies beyond it, where the outline follows one ellipse over most of its perimeter: neighbouring
slices that run on together from the head into the fetal trunk, which no rule comparing a slice with
its neighbours can catch. A slice whose outline is no ellipse (the skull base) is left as it is.

Example (a disc of radius 10 with a bar of 12 x 4 pixels on its side: the bar goes):
    >>> yy, xx = np.mgrid[:40, :50]
    >>> region = ((yy - 20) ** 2 + (xx - 18) ** 2 <= 100) | ((abs(yy - 20) <= 2) & (xx >= 27) & (xx < 40))
    >>> kept = trim_to_head_ellipses(region[None], grid_mm=1.0)[0]
    >>> bool(kept[20, 36]), bool(kept[20, 18]), int(region.sum() - kept.sum()) > 30
    (False, True, True)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

HEAD_ELLIPSE_SUPPORT = 0.6
"""A slice's region is cut to its head's ellipse (:func:`trim_to_head_ellipses`) only where the
region's outline follows that ellipse over this share of its perimeter: the skull's arc is most of
it, and a slice whose outline is no ellipse (the skull base) is left as it is."""
HEAD_ELLIPSE_MARGIN_MM = 3.0
"""What lies further than this outside a slice's head ellipse is cut (when it is over
:data:`HEAD_ELLIPSE_MIN_CUT` of the region)."""
HEAD_ELLIPSE_MIN_CUT = 0.08
"""A region loses what lies outside its head ellipse only when that is over this share of it."""
HEAD_ELLIPSE_TOLERANCE_MM = 3.0
"""An outline pixel within this distance of an ellipse supports it."""
MOMENT_ELLIPSE_SPILL = 0.005
"""A slice is left as it is, without a search, where no more than this share of it lies beyond the
margin of the ellipse of its own second moments: it is about an ellipse already (most slices)."""
HEAD_ELLIPSE_TRIES = 300
"""Ellipses through five outline pixels drawn at random per slice (a fixed seed): with half the
outline on the skull, some draw lies on it alone."""

def conics(points: NDArray) -> NDArray[np.float64]:
    """The conics ``a x^2 + b xy + c y^2 + d x + e y + f = 0`` through each set of five points
    ``[..., 5, 2]`` (their coefficients: the design matrix's signed 5 x 5 minors), or nearest a set of
    more points by least squares (``[m, 2]``, m > 5); ``[..., 6]`` of unit norm.

    Example (the circle of radius 2 about the origin, up to sign and scale):
        >>> t = np.linspace(0, 2 * np.pi, 5, endpoint=False)
        >>> q = conics(np.stack([2 * np.cos(t), 2 * np.sin(t)], 1))
        >>> (q / q[0]).round(6).tolist() == [1.0, 0.0, 1.0, 0.0, 0.0, -4.0]
        True
    """
    x, y = points[..., 0], points[..., 1]
    design = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=-1)
    if design.shape[-2] > 5:
        return np.linalg.svd(design)[2][..., -1, :]
    minors = np.linalg.det(np.stack([np.delete(design, i, axis=-1) for i in range(6)], axis=-3))
    q = minors * np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])
    return q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-300)


def ellipse_of(conic: NDArray) -> tuple[NDArray, NDArray, NDArray] | None:
    """A conic's centre, semi-axes and axes (columns), or None when it is no real ellipse."""
    a, b, c, d, e, f = conic
    quad = np.array([[a, b / 2], [b / 2, c]])
    if b * b - 4 * a * c >= 0:
        return None
    centre = np.linalg.solve(2 * quad, [-d, -e])
    level = -(centre @ quad @ centre + d * centre[0] + e * centre[1] + f)
    if abs(level) < 1e-12:                                   # a single point
        return None
    w, axes = np.linalg.eigh(quad / level)
    if np.any(w <= 0):
        return None
    return centre, 1.0 / np.sqrt(w), axes


def _sampson(conic: NDArray, points: NDArray) -> NDArray[np.float64]:
    """``[K, m]``: each point's first-order distance from each of the conics ``[K, 6]``."""
    x, y = points[:, 0], points[:, 1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    value = np.stack([x * x, x * y, y * y, x, y, one], 1) @ conic.T                 # [m, K]
    gx = np.stack([2 * x, y, zero, one, zero, zero], 1) @ conic.T
    gy = np.stack([zero, x, 2 * y, zero, one, zero], 1) @ conic.T
    return (np.abs(value) / np.maximum(np.hypot(gx, gy), 1e-12)).T


def head_ellipse(region: NDArray[np.bool_], grid_mm: float, rng: np.random.Generator,
                 ) -> tuple[tuple[NDArray, NDArray, NDArray], float] | None:
    """The ellipse that most of a slice's outline follows, and the share of its perimeter the
    outline supports; None for a region too small or an outline no ellipse follows.

    RANSAC: ellipses through :data:`HEAD_ELLIPSE_TRIES` random sets of five outline pixels; the one
    with most outline pixels within :data:`HEAD_ELLIPSE_TOLERANCE_MM` is refitted to them. What ran
    on beyond the skull (the fetal neck, the face) adds outline off that ellipse and does not move it.
    """
    outline = region & ~ndimage.binary_erosion(region)
    pixels = np.argwhere(outline).astype(np.float64)
    if len(pixels) < 20:
        return None
    mean = pixels.mean(0)
    scale = float(np.sqrt(((pixels - mean) ** 2).sum(1).mean()))          # conditioned: about unit radius
    points = (pixels - mean) / scale
    tol = HEAD_ELLIPSE_TOLERANCE_MM / grid_mm / scale
    drawn = conics(points[rng.integers(0, len(points), (HEAD_ELLIPSE_TRIES, 5))])
    is_ellipse = drawn[:, 1] ** 2 - 4 * drawn[:, 0] * drawn[:, 2] < 0
    near = _sampson(drawn, points) < tol
    best = int(np.argmax(np.where(is_ellipse, near.sum(1), -1)))
    if near[best].sum() < 6:
        return None
    fit = ellipse_of(conics(points[near[best]])) or ellipse_of(drawn[best])
    if fit is None:
        return None
    centre, semi, axes = mean + scale * fit[0], scale * fit[1], fit[2]
    t = np.linspace(0.0, 2 * np.pi, 72, endpoint=False)
    rim = np.round(centre + np.stack([semi[0] * np.cos(t), semi[1] * np.sin(t)], 1) @ axes.T).astype(int)
    inside = np.all((rim >= 0) & (rim < region.shape), axis=1)
    gap = ndimage.distance_transform_edt(~outline)
    supported = gap[tuple(np.clip(rim, 0, np.array(region.shape) - 1).T)] <= HEAD_ELLIPSE_TOLERANCE_MM / grid_mm + 0.5
    return (centre, semi, axes), float(np.mean(inside & supported))


def trim_to_head_ellipses(component: NDArray[np.bool_], grid_mm: float) -> NDArray[np.bool_]:
    """Each slice of a component ``[n, H, W]`` without what lies well outside its head's ellipse.

    Every plane cuts a skull in about an ellipse. Where a slice's outline follows one
    (:func:`head_ellipse`, over :data:`HEAD_ELLIPSE_SUPPORT` of its perimeter) and over
    :data:`HEAD_ELLIPSE_MIN_CUT` of the region lies more than :data:`HEAD_ELLIPSE_MARGIN_MM` outside
    it, that part goes: the fetal neck or face the region ran on into, in its own plane.

    Example (a disc of radius 12 px with a 20 px bar running off it: the bar goes, the disc stays):
        >>> r, c = np.mgrid[:60, :60]; disc = np.hypot(r - 25, c - 25) <= 12
        >>> bar = (abs(r - 25) <= 3) & (c > 30) & (c < 57)
        >>> out = trim_to_head_ellipses((disc | bar)[None], grid_mm=2.5)[0]
        >>> bool(out[disc].all()), int((out & ~disc).sum()) < 0.1 * int((bar & ~disc).sum())
        (True, True)
    """
    rng = np.random.default_rng(0)
    margin = HEAD_ELLIPSE_MARGIN_MM / grid_mm

    def outside(pixels: NDArray, centre: NDArray, semi: NDArray, axes: NDArray) -> NDArray[np.bool_]:
        u = (pixels - centre) @ axes
        return np.hypot(u[:, 0] / (semi[0] + margin), u[:, 1] / (semi[1] + margin)) > 1.0

    out = component.copy()
    for k in np.flatnonzero(component.reshape(len(component), -1).any(1)):
        pixels = np.argwhere(component[k]).astype(np.float64)
        if len(pixels) < 3:
            continue
        w, axes = np.linalg.eigh(np.cov(pixels.T))                      # the ellipse of the same moments
        if outside(pixels, pixels.mean(0), 2.0 * np.sqrt(np.maximum(w, 0.0)), axes).mean() <= MOMENT_ELLIPSE_SPILL:
            continue                                                    # the region is about an ellipse already
        fit = head_ellipse(component[k], grid_mm, rng)
        if fit is None or fit[1] < HEAD_ELLIPSE_SUPPORT:
            continue
        cut = outside(pixels, *fit[0])
        if cut.mean() > HEAD_ELLIPSE_MIN_CUT:
            out[k][tuple(pixels[cut].astype(int).T)] = False
    return out
