"""Test-time views: the network sees each slice in several exact symmetries of its pixel grid.

The network input is an ``L x L`` grid centred on the network frame's origin, so the 8 symmetries of
the square (rotations by ``k x 90`` degrees, with or without a left-right flip) map it onto itself
with no resampling. Each view's prediction maps back to a pose of the original slice exactly:

* a rotation ``np.rot90(x, k)`` moves the content at ``(x, y)`` to ``R^k (x, y)`` with
  ``R = [[0, 1], [-1, 0]]``, so the pose of the view is ``P R^-k`` and ``P = P_view R^k``;
* a flip (``x -> -x``) gives an image of the left-right mirrored brain: the atlas is symmetric
  about ``x = x0``, so the flipped slice is the slice at ``M P F`` (``M`` the atlas mirror, ``F =
  diag(-1, 1, 1)``), a proper pose, and ``P = M P_view R^k F``.

The MC-dropout samples are shared among the views (100 samples over 8 views: 13, 13, 13, 13, 12, ...),
so the head runs as often as with one view and only the trunk runs once per view. All views of all
slices go through the model in one call (each with the largest share of samples, the surplus
dropped), so a single streamed slice costs one call, not one per view. Their spread
then holds the disagreement between views as well as the dropout's: the mean pose averages errors
that depend on how the slice lies in the grid, and the variance ranks bad slices better
(``model_export/experiments/views_bench.py`` measures accuracy and cost per number of views,
docs/benchmarks.md; ``tests/inference/test_views.py`` checks the algebra on rendered phantom
slices).

Example:
    >>> import numpy as np
    >>> split_samples(100, 8)
    [13, 13, 13, 13, 12, 12, 12, 12]
    >>> img = np.arange(16.0).reshape(1, 4, 4)
    >>> bool(np.array_equal(view_images(view_images(img, 1, True), 3, False), np.flip(img, -1)))
    True
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from service.geometry import encodings, grid, twin

VIEW_COUNTS = (1, 4, 8)
"""1: the image as it is; 4: its four rotations; 8: rotations and flips (the symmetries of the square)."""
SHIPPED_VIEWS = 8
"""The views ``svrnet-train ship`` gives a model (``tta_views`` in its metadata): 4 take half the
inference time of 8 but give worse final poses and fewer accepted good slices (docs/reports/benchmark-history.md)."""

_R = np.array([[0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
_F = np.diag([-1.0, 1.0, 1.0, 1.0])


def view_count(n: int | str, field: str = "views") -> int:
    """``n`` as a number of views, :class:`ValueError` naming ``field`` unless it is one of
    :data:`VIEW_COUNTS` (a model file with another count would load and then fail every request).

    Example:
        >>> view_count("8")
        8
    """
    count = int(n)
    if count not in VIEW_COUNTS:
        raise ValueError(f"{field}: {n} is not one of {VIEW_COUNTS}")
    return count


def views(n: int) -> list[tuple[int, bool]]:
    """The ``(k, flip)`` of each of ``n`` views (``n`` in :data:`VIEW_COUNTS`)."""
    n = view_count(n)
    return [(k, flip) for flip in (False, True) for k in range(4)][:n] if n > 1 else [(0, False)]


def view_images(inputs: NDArray, k: int, flip: bool) -> NDArray:
    """Images ``[..., L, L]`` as view ``(k, flip)`` shows them: flipped left-right, then rotated ``k`` times."""
    x = np.flip(inputs, axis=-1) if flip else inputs
    return np.ascontiguousarray(np.rot90(x, k, axes=(-2, -1)))


def pose_from_view(poses: NDArray, k: int, flip: bool, plane_x_mm: float) -> NDArray[np.float64]:
    """Poses ``[..., 4, 4]`` predicted for view ``(k, flip)`` -> poses of the original slice."""
    out = np.asarray(poses, dtype=np.float64) @ np.linalg.matrix_power(_R, k)
    return twin.mirror(plane_x_mm) @ out @ _F if flip else out


@functools.lru_cache(maxsize=16)
def _grid_permutation(k: int, flip: bool) -> NDArray[np.intp] | None:
    """For grid labels: the point order that maps a view's label to the original's (the grid is
    closed under the symmetries of the square), or None if it is not."""
    q = np.concatenate([grid.TEMPLATE, np.ones((len(grid.TEMPLATE), 1))], axis=1)
    turned = (np.linalg.matrix_power(_R, k) @ (_F if flip else np.eye(4)) @ q.T).T[:, :3]
    dist = np.linalg.norm(turned[:, None] - grid.TEMPLATE[None], axis=-1)
    perm = dist.argmin(1)
    return perm if np.allclose(dist[np.arange(len(perm)), perm], 0.0, atol=1e-9) else None


def labels_from_view(labels: NDArray, label_type: str, k: int, flip: bool, plane_x_mm: float) -> NDArray[np.float64]:
    """Labels ``[..., D]`` predicted for view ``(k, flip)`` -> labels of the original slice: for grid
    labels a reordering of the points (and the mirror for flips), exact also for predictions that are
    not a rigid pose; otherwise through the pose (:func:`pose_from_view`)."""
    lab = np.asarray(labels, dtype=np.float64)
    perm = _grid_permutation(k, flip) if label_type == "grid" and lab.shape[-1] == 3 * len(grid.TEMPLATE) else None
    if perm is None:
        return encodings.encode(label_type, pose_from_view(encodings.decode(label_type, lab), k, flip, plane_x_mm))
    pts = lab.reshape(lab.shape[:-1] + (-1, 3))[..., perm, :]
    return (twin.mirror_points(pts, plane_x_mm) if flip else pts).reshape(lab.shape)


def split_samples(total: int, n_views: int) -> list[int]:
    """``total`` MC samples shared among ``n_views`` views as evenly as possible (0 stays 0: one
    deterministic pass per view)."""
    if total <= 0:
        return [0] * n_views
    n_views = min(n_views, total)
    return [total // n_views + (i < total % n_views) for i in range(n_views)]


def sample_views(run: Callable[[NDArray, int], NDArray], inputs: NDArray, mc_samples: int, label_type: str,
                 plane_x_mm: float, n_views: int) -> NDArray:
    """MC labels ``[B, N, D]`` of the original slices from ``n_views`` views.

    Args:
        run: ``(images [B, L, L], n) -> labels [B, n, D]`` of one model (``n = 0``: one deterministic pass).
        inputs: the network inputs ``[B, L, L]``.
        mc_samples: the samples in all (``N``; with 0, one deterministic pass per view).
    """
    if n_views == 1:
        return run(inputs, mc_samples)
    counts = split_samples(mc_samples, n_views)
    shown = views(n_views)[:len(counts)]
    b = len(inputs)
    labels = run(np.concatenate([view_images(inputs, k, flip) for k, flip in shown]), max(counts))
    return np.concatenate([labels_from_view(labels[i * b:(i + 1) * b, :max(n, 1)], label_type, k, flip, plane_x_mm)
                           for i, ((k, flip), n) in enumerate(zip(shown, counts))], axis=1)
