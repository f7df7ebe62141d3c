"""The output grid and the trilinear interpolation shared by every stage of the reconstruction.

Interpolation follows "grid-constant zero" semantics: a point's value is the trilinear blend of its
8 surrounding voxels, and voxels outside the grid count as 0. :func:`interpolation_matrix` builds
exactly that linear map as a sparse matrix (rows = samples, columns = voxels), so the forward
operator and its adjoint (the transpose, i.e. trilinear splatting) are exact transposes of each other
by construction. :func:`trilinear` evaluates the same interpolant together with its exact gradient
(used by the slice registration).

Example:
    >>> import numpy as np
    >>> g = make_grid(1.0, ([0.0, 0.0, 0.0], [3.0, 3.0, 3.0]))
    >>> g.shape
    (4, 4, 4)
    >>> vol = np.arange(64, dtype=np.float32).reshape(4, 4, 4)
    >>> val, grad = trilinear(vol, np.array([[1.5, 1.0, 2.0]]), gradient=True)
    >>> float(val[0]), grad[0].tolist()       # 16 * 1.5 + 4 * 1 + 2
    (30.0, [16.0, 4.0, 1.0])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import sparse

from service.core.errors import InvalidParameter
from service.geometry.frames import voxels_covering
from service.geometry.pose import apply

_CORNERS = np.array([[dx, dy, dz] for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)])


@dataclass(frozen=True)
class Grid:
    """A 3D voxel grid in atlas space.

    Attributes:
        affine: voxel index ``(i, j, k, 1)`` -> atlas RAS mm (``4 x 4``).
        shape: ``(I, J, K)``.
    """

    affine: NDArray[np.float64]
    shape: tuple[int, int, int]

    @property
    def spacing(self) -> NDArray[np.float64]:
        """Voxel sizes (mm) along ``i, j, k``."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    @property
    def bounds_mm(self) -> NDArray[np.float64]:
        """``[[lower], [upper]]``: the atlas positions of the first and the last voxel centre."""
        lower = self.affine[:3, 3]
        return np.stack([lower, lower + (np.array(self.shape) - 1) * self.spacing])

    @property
    def size(self) -> int:
        """Number of voxels."""
        return int(np.prod(self.shape))

    def voxel_of(self, points: ArrayLike) -> NDArray[np.float64]:
        """Continuous voxel indices ``[..., 3]`` of atlas points ``[..., 3]``."""
        return apply(np.linalg.inv(self.affine), points)

    def gradient_to_world(self, grad_voxel: NDArray) -> NDArray:
        """Convert gradients ``[..., 3]`` w.r.t. voxel index into gradients w.r.t. atlas mm."""
        jac = np.linalg.inv(self.affine[:3, :3]).astype(grad_voxel.dtype)   # d voxel / d mm
        return grad_voxel @ jac


def make_grid(resolution_mm: float, bounds_mm: ArrayLike) -> Grid:
    """An axis-aligned (RAS) isotropic grid covering ``bounds_mm = (lower [3], upper [3])``.

    The grid is centred on the box; its extent is rounded up to whole voxels.

    Args:
        resolution_mm: voxel size (mm).
        bounds_mm: ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` in atlas RAS mm.

    Returns:
        The :class:`Grid` (affine with positive diagonal ``resolution_mm``).
    """
    lo, hi = np.asarray(bounds_mm, dtype=np.float64).reshape(2, 3)
    if resolution_mm <= 0 or np.any(hi < lo):
        raise ValueError("make_grid: resolution must be > 0 and bounds ordered (lower, upper)")
    shape = voxels_covering(hi - lo, resolution_mm) + 1                   # a whole number of voxels stays whole
    centre = (lo + hi) / 2.0
    affine = np.diag([resolution_mm] * 3 + [1.0])
    affine[:3, 3] = centre - (shape - 1) / 2.0 * resolution_mm
    return Grid(affine, tuple(int(s) for s in shape))


MAX_EXTENT_MM = 250.0
"""The widest a reconstruction's field of view gets along an axis (mm): twice a term brain's length.
Slices placed farther apart than that (poses a client sent, or a stage that went astray) are not
followed: the box is cut to this extent about the median of the points, where most of them are."""


MAX_VOLUME_VOXELS = 16_000_000
"""The most voxels a reconstruction's volume holds. A job keeps a few tens of bytes a voxel at its
output resolution; this many keep a job of a few stacks within 2 GB (docs/reconstruction.md,
"Time and memory by voxel size")."""
FINEST_STEP_MM = 0.05
"""The voxel sizes :func:`check_volume_size` suggests are multiples of this."""


def check_volume_size(grid: Grid, where: str = "where the slices lie") -> None:
    """Refuse a volume of more than :data:`MAX_VOLUME_VOXELS`: :class:`InvalidParameter` naming
    ``resolution_mm``, its field of view (``where`` says what it covers) and the finest voxel size that
    field of view allows.

    Example (a box of 150 mm, at 1 mm and at 0.3 mm):
        >>> check_volume_size(make_grid(1.0, ([0.0, 0, 0], [150, 150, 150])))
        >>> check_volume_size(make_grid(0.3, ([0.0, 0, 0], [150, 150, 150])))
        Traceback (most recent call last):
        ...
        service.core.errors.InvalidParameter: resolution_mm: the volume's field of view (150 x 150 x 150 mm, where the slices lie) at 0.3 mm holds 125,751,501 voxels, more than a reconstruction may (16,000,000); ask for 0.60 mm or coarser
    """
    if grid.size <= MAX_VOLUME_VOXELS:
        return
    resolution = float(grid.spacing[0])
    bounds = grid.bounds_mm
    steps = int(np.ceil(resolution * (grid.size / MAX_VOLUME_VOXELS) ** (1 / 3) / FINEST_STEP_MM))
    while make_grid(round(steps * FINEST_STEP_MM, 2), bounds).size > MAX_VOLUME_VOXELS:   # as the answer prints it
        steps += 1
    finest = round(steps * FINEST_STEP_MM, 2)
    extent = " x ".join(f"{e:.0f}" for e in bounds[1] - bounds[0])
    raise InvalidParameter(f"resolution_mm: the volume's field of view ({extent} mm, {where}) at "
                           f"{resolution:g} mm holds {grid.size:,} voxels, more than a reconstruction may "
                           f"({MAX_VOLUME_VOXELS:,}); ask for {finest:.2f} mm or coarser")


def check_brain_fits(brain_mm3: float, extent_mm: ArrayLike, resolution_mm: float, margin_mm: float) -> None:
    """Refuse before a job starts a ``resolution_mm`` at which the brain alone (``brain_mm3``, what
    the masks mark) would hold more than :data:`MAX_VOLUME_VOXELS`: every volume that holds it holds
    more. The finest voxel size the answer names is that of the box around it (``extent_mm``, with
    ``margin_mm`` each side), as the job's own check (:func:`check_volume_size`) would name it.

    Example (a brain of 400 ml in a box of 100 x 90 x 80 mm, at 0.8 mm and at 0.25 mm):
        >>> check_brain_fits(400e3, [100, 90, 80], 0.8, 5.0)
        >>> check_brain_fits(400e3, [100, 90, 80], 0.25, 5.0)
        Traceback (most recent call last):
        ...
        service.core.errors.InvalidParameter: resolution_mm: the volume's field of view (110 x 100 x 90 mm, where the masks mark the brain) at 0.25 mm holds 63,839,601 voxels, more than a reconstruction may (16,000,000); ask for 0.40 mm or coarser
    """
    if brain_mm3 / resolution_mm ** 3 <= MAX_VOLUME_VOXELS:
        return
    half = (np.asarray(extent_mm, np.float64) + 2 * margin_mm) / 2
    check_volume_size(make_grid(resolution_mm, np.stack([-half, half])), where="where the masks mark the brain")


def bounds_of(points: ArrayLike, margin_mm: float, max_extent_mm: float = MAX_EXTENT_MM) -> NDArray[np.float64]:
    """``[[lower], [upper]]`` bounding box of points ``[N, 3]`` enlarged by ``margin_mm`` on each side,
    at most ``max_extent_mm`` wide along an axis (there centred on the points' median).

    Example:
        >>> bounds_of([[0.0, 0, 0], [10, 4, 2]], 1.0).tolist()
        [[-1.0, -1.0, -1.0], [11.0, 5.0, 3.0]]
        >>> bounds_of([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [5000, 0, 0]], 1.0, max_extent_mm=100.0)[:, 0].tolist()
        [-48.5, 51.5]
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    box = np.stack([p.min(axis=0) - margin_mm, p.max(axis=0) + margin_mm])
    wide = box[1] - box[0] > max_extent_mm
    if wide.any():
        middle = np.median(p[:, wide], axis=0)
        box[:, wide] = np.stack([middle - max_extent_mm / 2, middle + max_extent_mm / 2])
    return box


def bounds_within(bounds_mm: ArrayLike, limit_mm: ArrayLike) -> NDArray[np.float64]:
    """The part of the box ``bounds_mm`` inside the box ``limit_mm`` (both ``[[lower], [upper]]``);
    ``limit_mm`` itself where they do not overlap.

    Example:
        >>> bounds_within([[0.0, 0, 0], [10, 10, 10]], [[5.0, -5, 0], [20, 5, 10]]).tolist()
        [[5.0, 0.0, 0.0], [10.0, 5.0, 10.0]]
        >>> bounds_within([[0.0, 0, 0], [1, 1, 1]], [[5.0, 5, 5], [6, 6, 6]]).tolist()
        [[5.0, 5.0, 5.0], [6.0, 6.0, 6.0]]
    """
    box, limit = np.asarray(bounds_mm, np.float64), np.asarray(limit_mm, np.float64)
    out = np.stack([np.maximum(box[0], limit[0]), np.minimum(box[1], limit[1])])
    return limit.copy() if np.any(out[1] <= out[0]) else out


def _corners(coords: NDArray, shape: tuple[int, int, int]) -> tuple[NDArray, NDArray, NDArray]:
    """Base index, fractional offsets and per-corner validity of continuous voxel coordinates ``[N, 3]``."""
    c = np.asarray(coords, dtype=np.float64)
    base = np.floor(c)
    frac = (c - base).astype(np.float32)
    i0 = base.astype(np.int64)
    dims = np.asarray(shape)
    # valid[axis][d]: is corner offset d (0 or 1) inside the grid along axis?
    valid = [[(i0[:, a] + d >= 0) & (i0[:, a] + d < dims[a]) for d in (0, 1)] for a in range(3)]
    return i0, frac, valid


def trilinear_entries(coords: NDArray, shape: tuple[int, int, int]) -> tuple[NDArray, NDArray]:
    """Flat voxel indices ``[N, 8]`` and weights ``[N, 8]`` (float32) of trilinear interpolation.

    Indices are int32 when the grid allows it (int64 otherwise). Corners outside the grid get
    weight 0 (and a harmless in-range index).
    """
    i0, frac, valid = _corners(coords, shape)
    n = len(i0)
    idx = np.empty((n, 8), np.int32 if int(np.prod(shape)) < np.iinfo(np.int32).max else np.int64)
    w = np.empty((n, 8), np.float32)
    sj, sk = shape[1] * shape[2], shape[2]
    flat0 = i0[:, 0] * sj + i0[:, 1] * sk + i0[:, 2]
    for c, (dx, dy, dz) in enumerate(_CORNERS):
        wx = frac[:, 0] if dx else 1.0 - frac[:, 0]
        wy = frac[:, 1] if dy else 1.0 - frac[:, 1]
        wz = frac[:, 2] if dz else 1.0 - frac[:, 2]
        ok = valid[0][dx] & valid[1][dy] & valid[2][dz]
        w[:, c] = np.where(ok, wx * wy * wz, 0.0)
        idx[:, c] = np.where(ok, flat0 + dx * sj + dy * sk + dz, 0)
    return idx, w


ROWS_PER_PART = 1 << 16
"""Rows whose entries :func:`interpolation_matrix` works out at a time: the temporaries (base indices,
offsets, corner weights: several times the entries they make) are one part's, not every row's,
beside the matrix itself."""


def interpolation_matrix(coords: NDArray, shape: tuple[int, int, int], point_weights: ArrayLike | None = None,
                         dtype: type = np.float32, rows_per_part: int = ROWS_PER_PART) -> sparse.csr_matrix:
    """Sparse ``[N, I*J*K]`` matrix of ``N`` weighted sums of trilinear samples.

    Args:
        coords: ``[N, Q, 3]`` continuous voxel indices: ``Q`` sample points per row.
        shape: grid shape.
        point_weights: ``[Q]`` or ``[N, Q]`` weights of the points of a row (default 1).
        dtype: value type of the matrix.
        rows_per_part: rows whose entries are worked out at a time (:data:`ROWS_PER_PART`).

    Returns:
        CSR matrix ``M`` with ``(M @ x.ravel())[n] = sum_q w[n, q] * trilinear(x, coords[n, q])``.
        Its transpose is the exact adjoint (trilinear splatting).
    """
    c = np.asarray(coords)
    n, q = c.shape[:2]
    size = int(np.prod(shape))
    small = max(size, n * q * 8) < np.iinfo(np.int32).max
    index_dtype = np.int32 if small else np.int64
    pw = None if point_weights is None else np.broadcast_to(np.asarray(point_weights, dtype=np.float32), (n, q))
    data, indices = np.empty(n * q * 8, dtype), np.empty(n * q * 8, index_dtype)
    step = max(1, rows_per_part)
    for a in range(0, n, step):
        b = min(a + step, n)
        idx, w = trilinear_entries(c[a:b].reshape(-1, 3).astype(np.float64, copy=False), shape)
        if pw is not None:
            w *= pw[a:b].reshape(-1, 1)
        data[a * q * 8:b * q * 8], indices[a * q * 8:b * q * 8] = w.ravel(), idx.ravel()
    indptr = np.arange(0, n * q * 8 + 1, q * 8, dtype=index_dtype)
    return sparse.csr_matrix((data, indices, indptr), shape=(n, size))


def trilinear(volume: NDArray, coords: NDArray, gradient: bool = False) -> tuple[NDArray, NDArray | None]:
    """Trilinear values ``[N]`` at continuous voxel indices ``[N, 3]`` and, optionally, their gradient.

    The gradient ``[N, 3]`` (w.r.t. voxel index) is the exact derivative of the interpolant (piecewise
    constant across voxel faces), consistent with the values. Outside the grid the volume is 0.
    """
    vol = np.asarray(volume, dtype=np.float32)
    flat = vol.ravel()
    shape = vol.shape
    i0, frac, valid = _corners(coords, shape)
    sj, sk = shape[1] * shape[2], shape[2]
    flat0 = i0[:, 0] * sj + i0[:, 1] * sk + i0[:, 2]
    n = len(i0)
    val = np.zeros(n, np.float32)
    grad = np.zeros((n, 3), np.float32) if gradient else None
    one = np.float32(1.0)
    for dx, dy, dz in _CORNERS:
        ok = valid[0][dx] & valid[1][dy] & valid[2][dz]
        v = np.where(ok, flat[np.where(ok, flat0 + dx * sj + dy * sk + dz, 0)], 0.0).astype(np.float32)
        wx = frac[:, 0] if dx else one - frac[:, 0]
        wy = frac[:, 1] if dy else one - frac[:, 1]
        wz = frac[:, 2] if dz else one - frac[:, 2]
        val += wx * wy * wz * v
        if gradient:
            sx, sy, sz = (1.0 if dx else -1.0), (1.0 if dy else -1.0), (1.0 if dz else -1.0)
            grad[:, 0] += sx * wy * wz * v
            grad[:, 1] += sy * wx * wz * v
            grad[:, 2] += sz * wx * wy * v
    return val, grad
