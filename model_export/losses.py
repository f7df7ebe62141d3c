"""Training losses for point labels, plain and mirror-aware (issue 12).

A slice and its left-right twin render the same image (:mod:`service.geometry.twin`), so the
target is two-valued and a plain regression learns the average of the twins. Three losses, all on
point labels (``anchor`` or ``grid``: ``P`` points of ``(x, y, z)`` in atlas mm) and all measured in
the network's normalised units ``(label - mean) / scale``:

* ``l2`` -- the paper's multi-loss: mean over points of the Euclidean distance (times 3, so that for
  the three anchors it equals the sum of the three branch losses of the shipped recipe);
* ``min`` -- the same distance to whichever of {label, twin(label)} is nearer, per slice;
* ``invariant`` -- a loss that is mirror-invariant by construction and continuous everywhere. The
  twin keeps every point's ``(y, z)`` and negates every offset ``a_i = x_i - x0`` from the symmetry
  plane, all at once. So the ``(y, z)`` parts are compared directly, and the offsets through the
  sign-invariant outer product ``a a^T`` (the Veronese map of R^P / {+-1}):
  ``|â â^T - a a^T|_F / (|â| + |a|)``, which near ``â = a`` lies between ``|â - a| / sqrt 2`` (an
  error across ``a``, the offsets' pattern) and ``|â - a|`` (an error along ``a``, how far the slice
  lies from the plane as a whole), the same near ``â = -a``, and smooth across ``a = 0`` (sagittal
  slices near the midline, where the two twins meet and the ``min`` switches branch). The network's output stays a plain point label
  of one of the twins; which one (the branch) is left to the stack (the service's consistency
  stage), because a single slice of a symmetric atlas cannot decide it.

Example:
    >>> import torch
    >>> y = torch.tensor([[10.0, 1.0, 2.0, -5.0, 3.0, 4.0]])      # two points
    >>> tw = y.clone(); tw[:, 0::3] *= -1                          # its twin (plane x0 = 0)
    >>> scale, mean = torch.ones(6), torch.zeros(6)
    >>> [round(float(point_loss(tw, y, mean, scale, k)[0]), 3) for k in ("l2", "min", "invariant")]
    [45.0, 0.0, 0.0]
"""

from __future__ import annotations

import torch

from service.geometry.twin import DEFAULT_PLANE_X_MM, POINT_LABELS

LOSSES = ("l2", "min", "invariant")
EPS = 1e-3
TINY = 1e-12


def twin_points(labels: torch.Tensor, plane_x_mm: float = DEFAULT_PLANE_X_MM) -> torch.Tensor:
    """Point labels ``[B, 3P]`` (atlas mm) with every ``x`` mirrored: ``x -> 2 x0 - x`` (torch).

    Example:
        >>> twin_points(torch.tensor([[3.0, 4.0, 5.0]]), 1.0).tolist()
        [[-1.0, 4.0, 5.0]]
    """
    out = labels.clone()
    out[:, 0::3] = 2.0 * plane_x_mm - labels[:, 0::3]
    return out


def _point_distances(pred_n: torch.Tensor, target_n: torch.Tensor) -> torch.Tensor:
    """Per-slice loss ``[B]``: 3 x mean over points of the normalised Euclidean distance."""
    d = (pred_n - target_n).reshape(len(pred_n), -1, 3)
    return 3.0 * torch.linalg.vector_norm(d, dim=-1).mean(-1)


def point_loss(pred: torch.Tensor, target: torch.Tensor, mean: torch.Tensor, scale: torch.Tensor,
               kind: str = "l2", plane_x_mm: float = DEFAULT_PLANE_X_MM) -> torch.Tensor:
    """Per-slice losses ``[B]`` of predicted against true point labels, both ``[B, 3P]`` in atlas mm.

    Args:
        pred, target: point labels in atlas mm.
        mean, scale: the model's label normalisation ``[3P]`` (losses are in ``(label - mean) / scale``).
        kind: ``l2``, ``min`` or ``invariant`` (see the module docstring).
        plane_x_mm: the atlas symmetry plane ``x0``.
    """
    if kind not in LOSSES:
        raise ValueError(f"unknown loss {kind!r}; expected one of {LOSSES}")
    norm = lambda v: (v - mean) / scale  # noqa: E731
    if kind == "l2":
        return _point_distances(norm(pred), norm(target))
    if kind == "min":
        return torch.minimum(_point_distances(norm(pred), norm(target)),
                             _point_distances(norm(pred), norm(twin_points(target, plane_x_mm))))
    b = len(pred)
    sx = scale[0::3]
    a_hat = ((pred[:, 0::3] - plane_x_mm) / sx)                      # [B, P] offsets from the plane
    a = ((target[:, 0::3] - plane_x_mm) / sx)
    yz = (norm(pred) - norm(target)).reshape(b, -1, 3)[..., 1:]
    yz_term = torch.linalg.vector_norm(yz, dim=-1).mean(-1)
    # With u = â - a and v = â + a: â â^T - a a^T = (u v^T + v u^T) / 2, whose squared Frobenius norm is
    # (|u|^2 |v|^2 + (u . v)^2) / 2 -- no cancellation near either twin (u -> 0 or v -> 0).
    u, v = a_hat - a, a_hat + a
    sq = 0.5 * ((u * u).sum(-1) * (v * v).sum(-1) + (u * v).sum(-1) ** 2)
    frob = torch.sqrt(sq + TINY) - TINY ** 0.5                         # finite gradient at 0
    denom = torch.linalg.vector_norm(a_hat, dim=-1) + torch.linalg.vector_norm(a, dim=-1) + EPS
    n_points = a.shape[1]
    x_term = (2.0 ** 0.5) * frob / denom / n_points ** 0.5           # RMS offset error per point (x1 to x1.41)
    return 3.0 * (yz_term + x_term)


def check_label_type(label_type: str, kind: str) -> None:
    """Mirror-aware losses need point labels (their twin is a mirror of each point)."""
    if kind != "l2" and label_type not in POINT_LABELS:
        raise ValueError(f"the {kind!r} loss needs a point label ({POINT_LABELS}); got {label_type!r}")
