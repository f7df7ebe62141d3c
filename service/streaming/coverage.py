"""How much of the fetal brain the accepted slices of a session already sample, and where the gaps are.

The brain's extent in atlas space comes from the session itself, not from an atlas of one age:
the convex hull of the brain pixels of every slice that shows brain (accepted or not: a stack whose
middle slices alone were accepted still shows how far the brain reaches), placed at their poses,
less what lies further than :data:`REACH_THICKNESS` of a slice thickness from any of those pixels (the hull bridges the
brain's concavities, below the frontal lobes and between the temporal poles, where no stack can
add anything). A point of that brain is **covered** when an accepted slice passes through it:
within half the slice's thickness of its plane (the slice profile), inside its brain mask (one
pixel of slack). That is what a
slice-to-volume reconstruction needs of every voxel. The uncovered points form the **gaps**; each
gap, a 3D connected region, is reported by its centre, its thinnest direction (``normal``: slices
stacked along it fill the gap fastest), its extent along that normal and its volume.

Example (one stack of 3 mm slices every 3 mm, one slice not accepted):
    >>> import numpy as np
    >>> shown = []
    >>> for k in range(6):
    ...     a = np.diag([1.0, 1.0, 3.0, 1.0]); a[:3, 3] = (-20, -20, 3.0 * k)
    ...     shown.append(CoveredSlice(a, np.ones((41, 41), bool)))
    >>> c = coverage([s for k, s in enumerate(shown) if k != 3], shown)
    >>> round(c.brain_fraction, 2), len(c.gaps), [round(v, 1) for v in c.gaps[0].normal]
    (0.75, 1, [0.0, 0.0, 1.0])
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError, cKDTree

from service.inference.acceptance import ATLAS_CENTRE_MM

GRID_MM = 2.0
"""Spacing of the atlas-space grid coverage is counted on."""
MAX_HULL_POINTS = 4000
"""Brain pixels kept (evenly) to build the hull: enough for its shape, cheap to build."""
HULL_TOLERANCE_MM = 1e-6
"""A grid point this near a face of the hull, outside it, still counts as inside (points on a face)."""
REACH_THICKNESS = 0.6
"""A point of the hull is brain within this many slice thicknesses of a brain pixel the slices show:
the middle between two neighbouring slices of a stack is, the hull's bridge over the brain's
concavities is not: counted so, simulated sessions read as covered as the truth says they are,
where the hull alone reads a false gap below the frontal lobes (the figures: docs/realtime.md)."""
MIN_GAP_ML = 0.1
MAX_GAPS = 5
BRAIN_REACH_MM = 90.0
"""Brain pixels further than this from the atlas brain's centre
(:data:`~service.inference.acceptance.ATLAS_CENTRE_MM`) are left out: the largest atlas brains reach
about 60 mm from it, and a slice's mask drawn over its whole field of view (up to a metre a side)
would otherwise make the grid, which grows with the cube of the pixels' extent, gigabytes."""
MAX_REACH_PIXELS = 2_000_000
"""Brain pixels kept (evenly, per slice) to tell which grid points lie within reach of one: at most
about this many over a session (48 MB), so that a session's memory limit, which counts its slices'
pixels, also bounds coverage's."""


@dataclass(frozen=True)
class CoveredSlice:
    """One accepted slice: ``atlas_from_voxel`` (voxel ``(i0, i1, 0, 1)``, third column normal x
    thickness) and its brain ``mask`` ``[n0, n1]``."""

    atlas_from_voxel: NDArray[np.float64]
    mask: NDArray[np.bool_]


@dataclass(frozen=True)
class Gap:
    centre_mm: list[float]
    normal: list[float]
    extent_mm: float
    volume_ml: float


@dataclass(frozen=True)
class Coverage:
    """``brain_fraction``: share of the brain's hull covered; ``gaps``: the largest uncovered regions;
    ``brain_volume_ml``: the hull's volume (0 when the accepted slices do not span a volume yet);
    ``measured``: whether the brain's extent is known (False: no accepted slice, or the slices do not
    span a volume yet; the fraction 0 and no gaps then say nothing of what is covered)."""

    brain_fraction: float
    brain_volume_ml: float
    gaps: list[Gap] = field(default_factory=list)
    measured: bool = True

    def report(self) -> dict:
        """The contract's ``coverage`` object, and ``measured``."""
        return {"brain_fraction": round(self.brain_fraction, 4), "brain_volume_ml": round(self.brain_volume_ml, 1),
                "gaps": [{"centre_mm": g.centre_mm, "normal": g.normal, "extent_mm": round(g.extent_mm, 1),
                          "volume_ml": round(g.volume_ml, 2)} for g in self.gaps], "measured": self.measured}


def brain_points(slices: list[CoveredSlice], every: bool = False) -> NDArray[np.float64]:
    """Atlas mm of the slices' brain pixels within :data:`BRAIN_REACH_MM` of the atlas brain's centre
    (an even subset of at most :data:`MAX_HULL_POINTS`, or ``every`` one, up to an even share of
    :data:`MAX_REACH_PIXELS` per slice: :func:`hull_points` takes the subset of those).

    Example (a mask over a 600 mm field of view keeps the pixels near the atlas brain alone):
        >>> a = np.diag([2.0, 2.0, 3.0, 1.0]); a[:3, 3] = (-300.0, -300.0, 0.0)
        >>> pts = brain_points([CoveredSlice(a, np.ones((300, 300), bool))], every=True)
        >>> len(pts) < 300 * 300 / 10, bool(np.abs(pts).max() < 100)
        (True, True)
    """
    pts = []
    share = max(1, MAX_REACH_PIXELS // max(1, len(slices)))
    for s in slices:
        idx = np.argwhere(np.asarray(s.mask))
        if len(idx):
            found = idx @ s.atlas_from_voxel[:3, :2].T + s.atlas_from_voxel[:3, 3]
            found = found[np.linalg.norm(found - ATLAS_CENTRE_MM, axis=1) <= BRAIN_REACH_MM]
            pts.append(found[:: max(1, -(-len(found) // share))])
    if not pts:
        return np.zeros((0, 3))
    found = np.concatenate(pts)
    return found if every else hull_points(found)


def hull_points(pixels: NDArray[np.float64]) -> NDArray[np.float64]:
    """An even subset of at most about :data:`MAX_HULL_POINTS` of the brain ``pixels`` to build the hull from."""
    return pixels[:: max(1, len(pixels) // MAX_HULL_POINTS)]


def coverage(slices: list[CoveredSlice], shown: list[CoveredSlice] | None = None) -> Coverage:
    """The coverage by the accepted ``slices`` of the brain that the slices ``shown`` (default: the
    same) show (see the module)."""
    shown = slices if shown is None else shown
    pixels = brain_points(shown, every=True)
    points = hull_points(pixels)
    if len(points) < 4 or not slices:
        return Coverage(0.0, 0.0, measured=False)
    lo = points.min(0) - GRID_MM
    shape = tuple(int(x) for x in np.ceil((points.max(0) + GRID_MM - lo) / GRID_MM) + 1)
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3) * GRID_MM + lo
    try:
        inside = inside_hull(ConvexHull(points), grid)
    except QhullError:                      # the slices are coplanar: no volume yet
        return Coverage(0.0, 0.0, measured=False)
    reach = REACH_THICKNESS * max(float(np.linalg.norm(s.atlas_from_voxel[:3, 2])) for s in shown)
    inside[np.flatnonzero(inside)] = cKDTree(pixels).query(grid[inside], distance_upper_bound=reach)[0] <= reach
    brain = grid[inside]
    covered = np.zeros(len(brain), bool)
    for s in slices:
        voxel = (brain - s.atlas_from_voxel[:3, 3]) @ np.linalg.inv(s.atlas_from_voxel[:3, :3]).T
        near = np.abs(voxel[:, 2]) <= 0.5
        i0, i1 = np.rint(voxel[near, 0]).astype(int), np.rint(voxel[near, 1]).astype(int)
        m = ndimage.binary_dilation(np.asarray(s.mask), iterations=1)
        ok = (i0 >= 0) & (i0 < m.shape[0]) & (i1 >= 0) & (i1 < m.shape[1])
        hit = np.zeros(int(near.sum()), bool)
        hit[ok] = m[i0[ok], i1[ok]]
        covered[np.flatnonzero(near)[hit]] = True
    voxel_ml = GRID_MM ** 3 / 1000.0
    volume_ml = float(inside.sum() * voxel_ml)
    holes = np.zeros(shape, bool)
    holes.reshape(-1)[np.flatnonzero(inside)[~covered]] = True
    return Coverage(float(covered.mean()) if len(covered) else 0.0, volume_ml, gaps(holes, lo))


def inside_hull(hull: ConvexHull, points: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Which ``points [n, 3]`` lie inside ``hull`` (on the inner side of every face, within
    :data:`HULL_TOLERANCE_MM`): one half-space test per face. Unlike locating each point in a
    Delaunay triangulation, this costs the same whatever the points' arrangement; a stack's brain
    pixels lie on a lattice of parallel planes, whose degenerate triangulation sent the point
    location to a search over every simplex (40 s for one stack of 20 slices on 2 cores).

    Example (the unit cube's hull, one point inside, one on a face, one outside):
        >>> cube = ConvexHull(np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float))
        >>> inside_hull(cube, np.array([[0.5, 0.5, 0.5], [1.0, 0.5, 0.5], [1.5, 0.5, 0.5]])).tolist()
        [True, True, False]
    """
    inside = np.ones(len(points), bool)
    for face in hull.equations:                 # unit outward normal and offset: n . x + d <= 0 inside
        inside &= points @ face[:3] + face[3] <= HULL_TOLERANCE_MM
    return inside


def gaps(holes: NDArray[np.bool_], origin_mm: NDArray) -> list[Gap]:
    """The largest connected regions of ``holes`` (a grid of :data:`GRID_MM` from ``origin_mm``)."""
    labels, n = ndimage.label(holes, structure=np.ones((3, 3, 3), bool))
    if n == 0:
        return []
    sizes = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    voxel_ml = GRID_MM ** 3 / 1000.0
    out = []
    for label in np.argsort(sizes)[::-1][:MAX_GAPS] + 1:
        if sizes[label - 1] * voxel_ml < MIN_GAP_ML:
            break
        pts = np.argwhere(labels == label) * GRID_MM + origin_mm
        centre = pts.mean(0)
        normal = np.linalg.eigh(np.cov((pts - centre).T) + 1e-9 * np.eye(3))[1][:, 0] if len(pts) > 1 else np.eye(3)[2]
        normal = normal * (1.0 if normal[np.argmax(np.abs(normal))] > 0 else -1.0)
        along = (pts - centre) @ normal
        out.append(Gap([round(float(x), 1) for x in centre], [round(float(x), 4) for x in normal],
                       float(along.max() - along.min() + GRID_MM), float(len(pts) * voxel_ml)))
    return out
