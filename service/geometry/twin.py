"""The left-right twin: atlas space is mirror-symmetric, so every slice image has two poses.

The atlas is (nearly) symmetric about its mid-sagittal plane ``x = x0`` (atlas RAS mm). The mirror
across that plane is ``M = [[-1, 0, 0, 2 x0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]`` and the
**twin** of a slice pose ``T`` (slice mm -> atlas mm) is::

    twin(T) = M @ T @ FLIP_NORMAL,        FLIP_NORMAL = diag(1, 1, -1, 1)

the slice reflected into the other hemisphere and seen from behind. ``M`` and ``FLIP_NORMAL`` are
both reflections, so the twin is a proper rigid transform; it is an involution
(``twin(twin(T)) == T``); for points of the slice plane (``z = 0``) it acts as ``M @ T``, so a slice
sampled at ``twin(T)`` from a symmetric volume is the slice sampled at ``T``, pixel for pixel.

* Point labels (anchor points, a grid of plane points): the twin mirrors every point's ``x``.
* Rotations: ``R' = diag(-1, 1, 1) @ R @ diag(1, 1, -1)``. An axial or coronal slice's twin is the
  same plane turned by 180 degrees about an in-plane axis (seen from behind); a sagittal slice's
  twin has the same orientation at the mirrored position.

Example:
    >>> import numpy as np
    >>> from service.geometry import se3
    >>> pose = se3.exp(np.array([0.3, -0.2, 0.5, 10.0, -4.0, 2.0]))
    >>> tw = twin(pose, plane_x_mm=1.2)
    >>> bool(np.isclose(np.linalg.det(tw[:3, :3]), 1.0)), bool(np.allclose(twin(tw, 1.2), pose))
    (True, True)
    >>> mirror_points(np.array([3.0, 4.0, 5.0]), plane_x_mm=1.2).round(6).tolist()
    [-0.6, 4.0, 5.0]
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import expit

from service.geometry import anchors, encodings

DEFAULT_PLANE_X_MM = 0.0
"""The mid-sagittal plane assumed for models whose metadata does not name one (atlas RAS mm)."""

FLIP_NORMAL = np.diag([1.0, 1.0, -1.0, 1.0])
"""Reverses a slice frame's normal (and so its z offsets): the "seen from behind" half of the twin."""

MEDOID_CANDIDATES = 16
"""Samples tried as the branch reference by :func:`align_samples` (cost ``O(M N)``, not ``O(N^2)``).
Under test-time views the samples come view by view (:func:`~service.inference.views.sample_views`),
so the first are the unturned picture's and the next view's: candidates spread over every view place
simulated acquisitions no better (docs/reports/accuracy-analyses.md, "The branch reference's candidates")."""

POINT_LABELS = ("anchor", "grid")
"""Label types made of atlas points of the slice plane: their twin mirrors each point's x."""


def mirror(plane_x_mm: float = DEFAULT_PLANE_X_MM) -> NDArray[np.float64]:
    """The ``4 x 4`` reflection across the plane ``x = plane_x_mm`` (an improper transform)."""
    m = np.diag([-1.0, 1.0, 1.0, 1.0])
    m[0, 3] = 2.0 * plane_x_mm
    return m


def twin(pose: ArrayLike, plane_x_mm: float = DEFAULT_PLANE_X_MM) -> NDArray[np.float64]:
    """Twin poses ``M @ T @ FLIP_NORMAL`` of poses ``[..., 4, 4]`` (proper rigid, an involution)."""
    t = np.array(pose, dtype=np.float64)               # a copy: edited in place below
    # M @ T negates the first row and moves x; @ FLIP_NORMAL negates the third column.
    t[..., 0, :] *= -1.0
    t[..., 0, 3] += 2.0 * plane_x_mm
    t[..., :, 2] *= -1.0
    return t


def mirror_points(points: ArrayLike, plane_x_mm: float = DEFAULT_PLANE_X_MM) -> NDArray[np.float64]:
    """Points ``[..., 3]`` reflected across the plane (``x -> 2 x0 - x``)."""
    p = np.array(points, dtype=np.float64)
    p[..., 0] = 2.0 * plane_x_mm - p[..., 0]
    return p


def twin_label(label_type: str, label: ArrayLike, plane_x_mm: float = DEFAULT_PLANE_X_MM) -> NDArray[np.float64]:
    """The twin of labels ``[..., D]`` of ``label_type``.

    Point labels mirror each point (exact, also for noisy predictions that are not a rigid pose);
    rotation + translation labels go through the pose: ``encode(twin(decode(label)))``.

    Example:
        >>> import numpy as np
        >>> from service.geometry import encodings, se3
        >>> pose = se3.exp(np.array([0.1, 0.7, -0.4, 3.0, 1.0, -2.0]))
        >>> all(np.allclose(twin_label(k, encodings.encode(k, pose), 0.5),
        ...                 encodings.encode(k, twin(pose, 0.5))) for k in encodings.LABEL_TYPES)
        True
    """
    lab = np.asarray(label, dtype=np.float64)
    if label_type in POINT_LABELS:
        pts = lab.reshape(lab.shape[:-1] + (-1, 3))
        return mirror_points(pts, plane_x_mm).reshape(lab.shape)
    enc = encodings.get(label_type)
    return enc.encode(twin(enc.decode(lab), plane_x_mm))


def twin_min_ed(pred: ArrayLike, true: ArrayLike, plane_x_mm: float = DEFAULT_PLANE_X_MM) -> NDArray[np.float64]:
    """Mirror-invariant error: the E.D. of ``pred`` to whichever of ``true`` and its twin is nearer.

    Example:
        >>> import numpy as np
        >>> from service.geometry import se3
        >>> pose = se3.exp(np.array([0.2, 0.1, 0.3, 20.0, 5.0, 0.0]))
        >>> float(twin_min_ed(twin(pose), pose))
        0.0
    """
    return np.minimum(anchors.ed(pred, true), anchors.ed(pred, twin(true, plane_x_mm)))


def twin_distance_mm(poses: ArrayLike, plane_x_mm: float = DEFAULT_PLANE_X_MM) -> NDArray[np.float64]:
    """``[...]`` the E.D. between each pose and its own twin: how far a slice moves if it belongs to
    the other hemisphere (small near the mid-sagittal plane, where the two are nearly one pose).

    Example:
        >>> import numpy as np
        >>> sagittal = np.array([[0.0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]])   # normal along x
        >>> lateral = sagittal.copy(); lateral[0, 3] = 6.0                                  # 6 mm off the plane
        >>> twin_distance_mm(np.stack([sagittal, lateral])).round(3).tolist()
        [0.0, 12.0]
    """
    p = np.asarray(poses, dtype=np.float64)
    return anchors.ed(p, twin(p, plane_x_mm))


def twin_risk(distance_mm: ArrayLike, logit: tuple[float, float]) -> NDArray[np.float64]:
    """The chance that a slice sits on its twin, from its distance to it (:func:`twin_distance_mm`):
    ``1 / (1 + exp(-(a + b d)))`` with ``logit = (a, b)``, a model's calibration
    (``twin_risk_logit``; ``b < 0``: the nearer the mid-sagittal plane, the likelier).

    Example:
        >>> twin_risk(np.array([0.0, 10.0]), (-1.0, -0.1)).round(3).tolist()
        [0.269, 0.119]
    """
    a, b = logit
    return expit(a + b * np.asarray(distance_mm, dtype=np.float64))


UNDECIDED_TWIN_CHANCE = 0.5
"""The chance that a slice whose branch nothing has decided (no stack model, no request, a slice
alone) sits on its mirror twin: a slice and its twin show one image, and the network's MC samples
split between them by the view they came from, not by the image."""


def undecided_twin_variance(distance_mm: ArrayLike) -> NDArray[np.float64]:
    """What the twin adds to the expected squared E.D. (mm^2) of a slice whose branch is undecided:
    :data:`UNDECIDED_TWIN_CHANCE` times its squared distance to its twin.

    Example:
        >>> undecided_twin_variance(np.array([0.0, 10.0])).tolist()
        [0.0, 50.0]
    """
    d = np.asarray(distance_mm, dtype=np.float64)
    return UNDECIDED_TWIN_CHANCE * d ** 2


def twin_variance(distance_mm: ArrayLike, logit: tuple[float, float]) -> NDArray[np.float64]:
    """What the twin adds to a slice's expected squared E.D. (mm^2): its chance of sitting on its
    twin (:func:`twin_risk`) times its squared distance to it; a slice on the plane adds nothing.

    Example:
        >>> twin_variance(np.array([0.0, 10.0]), (-1.0, -0.1)).round(2).tolist()
        [0.0, 11.92]
    """
    d = np.asarray(distance_mm, dtype=np.float64)
    return twin_risk(d, logit) * d ** 2


def nearer(pred: ArrayLike, true: ArrayLike, plane_x_mm: float = DEFAULT_PLANE_X_MM) -> NDArray[np.float64]:
    """``[..., 4, 4]`` per pose, ``true`` or its twin, whichever is nearer to ``pred`` (E.D.; ``true`` on a tie):
    the reference a mirror-invariant error is measured against (:func:`twin_min_ed`).

    Example:
        >>> import numpy as np
        >>> from service.geometry import se3
        >>> pose = se3.exp(np.array([0.2, 0.1, 0.3, 20.0, 5.0, 0.0]))
        >>> bool(np.allclose(nearer(twin(pose), pose), twin(pose)))
        True
    """
    t = np.asarray(true, dtype=np.float64)
    tw = twin(t, plane_x_mm)
    return np.where((anchors.ed(pred, t) <= anchors.ed(pred, tw))[..., None, None], t, tw)


def measure_plane_x(image: ArrayLike, affine: ArrayLike, max_shift_mm: float = 8.0) -> float:
    """The mid-sagittal plane ``x0`` of a volume: where its left-right mirror correlates best with it.

    The voxel axis most aligned with atlas ``x`` is flipped (an exact mirror about the grid's centre
    plane ``xc``); the mirror about ``x0`` is that flip shifted by ``2 (x0 - xc)``. The correlation
    is computed for every whole-voxel shift within ``max_shift_mm`` and refined by a parabola
    through the best three.

    Args:
        image: ``[I, J, K]`` intensities.
        affine: voxel -> RAS mm; its x-most voxel axis must be parallel to x (atlas grids are).

    Returns:
        ``x0`` in atlas mm.

    Example:
        >>> import numpy as np
        >>> aff = np.diag([0.5, 1.0, 1.0, 1.0]); aff[0, 3] = -10.0   # x = 0.5 i - 10
        >>> x = np.arange(41) * 0.5 - 10.0
        >>> vol = np.exp(-((x - 1.3) / 3.0) ** 2)[:, None, None] * np.ones((1, 4, 4))
        >>> round(measure_plane_x(vol, aff), 2)
        1.3
    """
    a = np.asarray(affine, dtype=np.float64)
    axis = int(np.argmax(np.abs(a[0, :3])))
    col = a[:3, axis]
    if np.linalg.norm(col[1:]) > 1e-6 * abs(col[0]):
        raise ValueError("the volume's voxel axes are not aligned with atlas x")
    step = col[0]                                          # signed mm per voxel along x
    vol = np.moveaxis(np.asarray(image, dtype=np.float64), axis, 0)
    n = vol.shape[0]
    xc = a[0, 3] + step * (n - 1) / 2.0                    # x of the grid's centre plane
    flipped = vol[::-1]
    max_s = max(1, int(np.ceil(2.0 * max_shift_mm / abs(step))))
    shifts = np.arange(-max_s, max_s + 1)
    scores = np.array([_overlap_correlation(vol, flipped, s) for s in shifts])
    k = int(np.argmax(scores))
    frac = 0.0
    if 0 < k < len(shifts) - 1:
        y0, y1, y2 = scores[k - 1], scores[k], scores[k + 1]
        denom = y0 - 2 * y1 + y2
        frac = 0.5 * (y0 - y2) / denom if denom < 0 else 0.0
    shift_vox = shifts[k] + frac
    # flipped[i] = vol[n - 1 - i]; comparing vol[i] with flipped[i - s] mirrors index i to
    # n - 1 - i + s, i.e. the mirror centre sits at index (n - 1 + s) / 2.
    return float(xc + step * shift_vox / 2.0)


def _overlap_correlation(a: NDArray, b: NDArray, shift: int) -> float:
    """Pearson correlation of ``a[i]`` with ``b[i - shift]`` over their overlap along axis 0."""
    if shift >= 0:
        x, y = a[shift:], b[: len(b) - shift]
    else:
        x, y = a[:shift], b[-shift:]
    x = x.ravel() - x.mean()
    y = y.ravel() - y.mean()
    denom = np.sqrt(np.dot(x, x) * np.dot(y, y))
    return float(np.dot(x, y) / denom) if denom > 0 else -1.0


def align_samples(poses: ArrayLike, plane_x_mm: float = DEFAULT_PLANE_X_MM) -> tuple[NDArray, NDArray]:
    """Put pose samples ``[..., N, 4, 4]`` on one branch: the majority branch of their twin-free medoid.

    Samples are compared by the anchor-point distance modulo the twin (``min(|a - b|,
    |a - twin(b)|)``, mean over the three anchors); of the first :data:`MEDOID_CANDIDATES` samples
    (a subset of a view's i.i.d. MC samples, or of the first views') the one minimising the sum of these
    distances to all samples (a medoid of the quotient space) fixes a branch, every sample is replaced
    by whichever of itself and its twin is nearer that medoid, and finally the branch holding the
    greater part of the samples becomes the reference (so a slice's reported pose is where most
    of its MC mass sat; on an even split, the first sample's branch).

    Returns:
        ``(aligned [..., N, 4, 4], flipped [..., N] bool)``: ``flipped`` marks the samples replaced
        by their twin, so ``flipped.mean(-1)`` is the MC mass that sat on the other twin (<= 0.5).

    Example:
        >>> import numpy as np
        >>> from service.geometry import se3
        >>> rng = np.random.default_rng(0)
        >>> base = se3.exp(np.array([0.4, 0.2, 0.1, 20.0, 5.0, 0.0]))
        >>> x = base @ se3.exp(rng.normal(0, 0.02, (10, 6)))
        >>> x[:3] = twin(x[:3])                      # 3 of 10 samples on the other twin
        >>> aligned, flipped = align_samples(x)
        >>> int(flipped.sum()), bool(np.allclose(aligned[:3], twin(x[:3])))
        (3, True)
    """
    x = np.asarray(poses, dtype=np.float64)
    pts = anchors.encode(x).reshape(x.shape[:-2] + (3, 3))          # [..., N, 3, 3]
    tw = mirror_points(pts, plane_x_mm)
    cand = pts[..., :MEDOID_CANDIDATES, :, :]                     # the first samples (MEDOID_CANDIDATES)
    direct = _pairwise_mean_distance(cand, pts)                    # [..., M, N]
    mirrored = _pairwise_mean_distance(cand, tw)
    medoid = np.argmin(np.minimum(direct, mirrored).sum(axis=-1), axis=-1)          # [...]
    take = np.expand_dims(medoid, (-1, -2))
    flipped = np.take_along_axis(mirrored, take, axis=-2)[..., 0, :] < np.take_along_axis(direct, take, axis=-2)[..., 0, :]
    share = flipped.mean(axis=-1)
    # An even split keeps the first sample's branch: a rule the mirror carries over (the medoid's own
    # would be settled by rounding, and a slice and its twin could answer on one branch).
    majority_twin = (share > 0.5) | ((share == 0.5) & flipped[..., 0])
    flipped = flipped ^ majority_twin[..., None]
    aligned = np.where(flipped[..., None, None], twin(x, plane_x_mm), x)
    return aligned, flipped


def _pairwise_mean_distance(a: NDArray, b: NDArray) -> NDArray:
    """``[..., N, M]``: mean over the point axis P of ``|a_n,p - b_m,p|`` for ``[..., N, P, 3]`` and
    ``[..., M, P, 3]`` (Gram matrices per point, no ``N x M x P x 3`` intermediate)."""
    a_p = np.moveaxis(a, -2, -3)                                   # [..., P, N, 3]
    b_p = np.moveaxis(b, -2, -3)
    sq = (np.sum(a_p * a_p, -1)[..., :, None] + np.sum(b_p * b_p, -1)[..., None, :]
          - 2.0 * a_p @ np.swapaxes(b_p, -1, -2))                   # [..., P, N, M]
    return np.sqrt(np.maximum(sq, 0.0)).mean(axis=-3)
