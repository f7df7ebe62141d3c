"""One stack's slices, made consistent: the twin branch decided from all of them, a motion-tolerant rigid fit.

Every slice ``k`` of a stack comes with the network's pose ``P_k`` (network frame -> atlas) and,
from the file, ``N_k`` = network frame <- scanner (the service's crop/centre composed with the
stack's voxel -> scanner map). Without motion all slices share one ``atlas_from_scanner``
``S = P_k @ N_k``. Each slice proposes ``S`` from its pose or from its twin's; the twin branch of
a whole stack is not rigid (its slices would run backwards along the normal), so the branch of
each slice is decidable from the others even when every single slice is ambiguous.

Steps (all slices at once, numpy only):

1. **Branch** (RANSAC): every usable slice and branch proposes ``S``; the proposal that explains
   most slices (MSAC cost of the anchor-point distance, each slice on its nearer branch) wins;
   each slice takes the branch nearer to it.
2. **Rigid fit** (IRLS): a Tukey-weighted Fréchet mean of the proposals (one Gauss-Newton step
   per round, from the RANSAC proposal), branches re-decided on the way: ``atlas_from_scanner``.
3. **Motion** (leave-one-out local model): each slice's pose predicted from the others, weighted
   by a Gaussian kernel over acquisition time; the acquisition order (sequential or interleaved)
   and the kernel width (down to rigid) are chosen by cross-validation of that prediction.
4. **Fusion**: each slice's pose becomes the inverse-variance mean of its own and the model's,
   with the network's error from its calibrated MC spread (or, without one, from acquisition
   neighbours) and the model's from the cross-validated residual; slices whose own pose
   disagrees with the model beyond what both errors explain are *inconsistent* (they take the
   model's pose). When fewer than
   :data:`MIN_INLIER_FRACTION` of the slices agree, or the model's error exceeds
   :data:`MAX_MODEL_ERROR_MM`, the stack is *undecidable* and nothing is changed.

Distances are the paper's E.D. (:func:`service.geometry.anchors.ed`, mm).

Example:
    >>> import numpy as np
    >>> from service.geometry import se3, twin
    >>> rng = np.random.default_rng(0)
    >>> n = np.stack([se3.exp(np.array([0, 0, 0, 0, 0, -3.0 * k])) for k in range(12)])   # slices 3 mm apart
    >>> s = se3.exp(np.array([0.3, -0.2, 0.4, 5.0, -2.0, 1.0]))
    >>> truth = s @ se3.inverse(n)
    >>> noisy = truth @ se3.exp(rng.normal(0, [0.05] * 3 + [2.0] * 3, (12, 6)))
    >>> noisy[::2] = twin.twin(noisy[::2])                  # half of them on the other twin
    >>> fit = fit_stack(noisy, n)
    >>> fit.decidable, int(fit.twinned.sum())
    (True, 6)
    >>> bool(ed(fit.poses, truth).mean() < ed(twin.twin(noisy[::2]), truth[::2]).mean())
    True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.geometry import se3, twin
from service.geometry.anchors import ed
from service.geometry.pose import make_pose

RANSAC_TAU_MM = 30.0
"""MSAC truncation of a slice's residual when scoring branch proposals (mm of E.D.)."""
MIN_INLIER_FRACTION = 0.5
"""A stack whose model explains fewer of its usable slices than this is undecidable."""
MAX_MODEL_ERROR_MM = 25.0
"""A stack whose model predicts its slices worse than this (cross-validated, network error removed)
has no common geometry (e.g. every slice moved independently): undecidable, nothing is changed."""
MIN_SLICES = 3
TUKEY_C = 4.685
MIN_SCALE_MM = 3.0
"""Floor of the robust residual scale (mm), so a near-perfect stack does not reject its noise."""
OUTLIER_K = 3.0
OUTLIER_FLOOR_MM = 15.0
"""A slice is inconsistent when its residual to the model exceeds ``max(K * sqrt(network^2 +
model^2), floor)``: K times what the two estimated errors together explain."""
IRLS_ROUNDS = 6
MEAN_TOL_RAD = 1e-7
"""Fréchet-mean tolerance of the stage (1e-7 rad moves an anchor 60 mm away by 6 nm)."""
BRANCH_MARGIN_MM = 5.0
MIN_STACK_BRANCH_MARGIN = 1.5
"""A stack whose twin fits a rigid stack less than this many times worse has not decided its branch."""
MIN_NOISE_MM = 0.1
"""Floor of a pose's expected error (mm), so an exact oracle still has a finite weight."""
BANDWIDTHS = (1.0, 2.0, 4.0, 8.0, np.inf)
"""Kernel widths (in acquisitions) tried by the cross-validation; ``inf`` is one rigid fit."""


@dataclass
class StackFit:
    """What the stage decided for one stack.

    Attributes:
        poses: ``[n, 4, 4]`` the consistent poses (network frame -> atlas).
        twinned: ``[n]`` slices whose pose is the twin of the network's.
        inconsistent: ``[n]`` slices whose own pose disagreed with the stack model.
        residual_mm: ``[n]`` E.D. between the network's pose (on its branch) and the model's.
        decidable: False where the slices do not agree on one stack (nothing was changed).
        atlas_from_scanner: ``4 x 4`` rigid fit (``None`` when undecidable).
        inlier_fraction: fraction of usable slices the stack model explains (not inconsistent).
        acquisition_order: the order chosen (``sequential``, ``interleaved-even-first``, ...).
        bandwidth: kernel width in acquisitions (``inf``: rigid, no motion needed).
        noise_mm, model_mm: estimated E.D. of a network pose and of the model's prediction.
        branch_margin: how many times worse the whole stack on its other twin fits one rigid
            stack (under :data:`MIN_STACK_BRANCH_MARGIN`: this stack does not decide its branch).
    """

    poses: NDArray[np.float64]
    twinned: NDArray[np.bool_]
    inconsistent: NDArray[np.bool_]
    residual_mm: NDArray[np.float64]
    decidable: bool
    atlas_from_scanner: NDArray[np.float64] | None = None
    inlier_fraction: float = 0.0
    acquisition_order: str = "unknown"
    bandwidth: float = np.inf
    noise_mm: float = float("nan")
    model_mm: float = float("nan")
    branch_margin: float = float("nan")

    @property
    def branch_decided(self) -> bool:
        """The stack's left-right branch is decided by its slices' order along the normal."""
        return bool(self.decidable and self.branch_margin >= MIN_STACK_BRANCH_MARGIN)


def acquisition_orders(n: int) -> dict[str, NDArray[np.int64]]:
    """Candidate acquisition times ``t[k]`` of slice ``k``: sequential, and interleaved by 2."""
    k = np.arange(n)
    half = (n + 1) // 2
    even_first = np.where(k % 2 == 0, k // 2, half + k // 2)
    odd_first = np.where(k % 2 == 1, k // 2, n // 2 + k // 2)
    return {"sequential": k, "interleaved-even-first": even_first, "interleaved-odd-first": odd_first}


def fit_stack(poses: ArrayLike, network_from_scanner: ArrayLike, usable: ArrayLike | None = None,
              plane_x_mm: float = twin.DEFAULT_PLANE_X_MM, noise_mm: ArrayLike | None = None) -> StackFit:
    """Make one stack's slice poses consistent (see the module docstring).

    Args:
        poses: ``[n, 4, 4]`` the network's poses (each on its MC-majority branch).
        network_from_scanner: ``[n, 4, 4]`` rigid maps from the scanner (stack) frame to each
            slice's network frame.
        usable: ``[n]`` slices allowed to vote (default all); the others only receive the model's pose.
        plane_x_mm: the atlas mid-sagittal plane of the twin.
        noise_mm: ``[n]`` the expected E.D. of each network pose (its calibrated MC spread). Motion
            that is independent from slice to slice cannot be told from network error by the poses
            alone; this tells them apart. Without it the error is estimated from acquisition
            neighbours (an upper bound: right for smooth motion, too trusting of the model for
            jittery motion).
    """
    p = np.asarray(poses, dtype=np.float64)
    nk = np.asarray(network_from_scanner, dtype=np.float64)
    n = len(p)
    use = np.ones(n, bool) if usable is None else np.asarray(usable, bool).copy()
    unchanged = StackFit(p.copy(), np.zeros(n, bool), np.zeros(n, bool), np.full(n, np.nan), False)
    if use.sum() < MIN_SLICES:
        return unchanged
    cand = np.stack([p, twin.twin(p, plane_x_mm)], axis=1)                 # [n, 2, 4, 4]
    proposals = cand @ nk[:, None]                                          # S = P_k N_k, [n, 2, 4, 4]
    inv_n = se3.inverse(nk)

    # 1. branch: RANSAC over the usable slices' proposals
    idx = np.flatnonzero(use)
    implied = proposals[idx][:, :, None] @ inv_n[None, None]                # [h, 2, n, 4, 4]
    res = ed(implied[:, :, :, None], cand[None, None])                      # [h, 2, n, 2]
    best = res.min(axis=-1)
    cost = (np.minimum(best, RANSAC_TAU_MM)[..., use] ** 2).sum(axis=-1)   # [h, 2]
    h, b = np.unravel_index(np.argmin(cost), cost.shape)
    branch = _branch(res[h, b])                                             # [n]

    # 2. rigid fit: IRLS with Tukey weights, branches re-decided each round
    s = proposals[idx[h], b]
    for _ in range(IRLS_ROUNDS):
        model = s @ inv_n                                                   # [n, 4, 4]
        both = ed(model[:, None], cand)                                     # [n, 2]
        branch = _branch(both)
        r = both[np.arange(n), branch]
        w = _tukey(r, _scale(r[use])) * use
        if w.sum() <= 0:
            return unchanged
        s = _local_models(proposals[np.arange(n), branch], s, w[None])[0]   # one Gauss-Newton step a round
    inliers = (w > 0) & use

    # 3. motion: leave-one-out local models over acquisition time, chosen by cross-validation
    own = cand[np.arange(n), branch]                                        # [n, 4, 4] each on its branch
    chosen = proposals[np.arange(n), branch]
    combos = [(name, t, bw) for name, t in acquisition_orders(n).items() for bw in BANDWIDTHS]
    all_w = np.stack([_loo_weights(t, bw, w) for _, t, bw in combos])        # [c, n, n]: all at once
    all_pred = _local_models(chosen, s, all_w) @ inv_n                       # [c, n, 4, 4]
    all_r = ed(all_pred, own[None])                                          # [c, n]
    c = int(np.argmin(np.median(all_r[:, inliers] ** 2, axis=1)))
    name, t, bw = combos[c]
    # branches again, against the local model (the rigid fit is off by the motion; near the
    # mid-sagittal plane that can exceed half the distance to the twin); then the stack's branch as
    # a whole by the rigid model (only the order along the normal tells a stack from its twin, and a
    # flexible motion model can bend to either order); then the model once more
    branch = _branch(ed(all_pred[c][:, None], cand))
    own = cand[np.arange(n), branch]
    chosen = proposals[np.arange(n), branch]
    margin = _branch_margin(proposals, cand, branch, inv_n, w, inliers)
    if margin < 1.0:                       # the whole stack's twin is the better rigid stack: take it
        branch, margin = 1 - branch, 1.0 / margin
        own = cand[np.arange(n), branch]
        chosen = proposals[np.arange(n), branch]
        s = se3.frechet_mean(chosen, np.maximum(w, 1e-12), tol=MEAN_TOL_RAD)
    predicted = _local_models(chosen, s, _loo_weights(t, bw, w)) @ inv_n
    r_loo = ed(predicted, own)
    best_score = float(np.median(r_loo[inliers] ** 2))

    # 4. fusion: inverse-variance weights from the network's and the model's estimated errors
    close = inliers & (r_loo <= np.percentile(r_loo[inliers], 90))         # trimmed: a few wild slices aside
    if noise_mm is not None:
        noise2_k = np.maximum(np.asarray(noise_mm, dtype=np.float64) ** 2, MIN_NOISE_MM ** 2)
        noise2 = float(np.mean(noise2_k[close]))
    else:
        noise2 = min(_neighbour_noise2(chosen, own, inv_n, t, inliers, best_score), best_score)
        noise2_k = np.full(n, noise2)
    residual2 = float(np.mean(r_loo[close] ** 2))
    model2 = max(residual2 - noise2, 1e-3 * residual2, MIN_NOISE_MM ** 2)
    alpha = model2 / (model2 + noise2_k)                                     # weight of each slice's own pose
    limit = np.maximum(OUTLIER_K * np.sqrt(noise2_k + model2), OUTLIER_FLOOR_MM)
    inconsistent = use & (r_loo > limit)
    fraction = float((use & ~inconsistent).sum() / use.sum())
    if fraction < MIN_INLIER_FRACTION or np.sqrt(model2) > MAX_MODEL_ERROR_MM:
        return StackFit(p.copy(), np.zeros(n, bool), np.zeros(n, bool), r_loo, False, s, fraction, name, float(bw),
                        float(np.sqrt(noise2)), float(np.sqrt(model2)))
    trust_own = use & ~inconsistent
    weights = np.stack([np.where(trust_own, alpha, 0.0), np.where(trust_own, 1.0 - alpha, 1.0)], axis=1)
    fused = se3.frechet_mean(np.stack([own, predicted], axis=1), weights, tol=MEAN_TOL_RAD)
    return StackFit(fused, branch == 1, inconsistent, r_loo, True, s, fraction, name, float(bw),
                    float(np.sqrt(noise2)), float(np.sqrt(model2)), margin)


def _branch_margin(proposals: NDArray, cand: NDArray, branch: NDArray, inv_n: NDArray, w: NDArray,
                   inliers: NDArray) -> float:
    """How many times worse one rigid stack explains the slices with every slice on its other twin
    (ratio of median squared leave-one-out E.D.). The whole stack's twin differs from the truth
    only in the order of its slices along the normal, which a rigid model sees and a flexible
    motion model can bend to; a network whose positions along the normal are poor leaves this
    ratio near 1: the branch is then not decided by this stack."""
    n = len(branch)
    rigid = np.ones((n, n)) * w[None]
    np.fill_diagonal(rigid, 0.0)
    scores = []
    for b in (branch, 1 - branch):
        chosen = proposals[np.arange(n), b]
        centre = se3.frechet_mean(chosen, np.maximum(w, 1e-12), tol=MEAN_TOL_RAD)
        r = ed(_local_models(chosen, centre, rigid) @ inv_n, cand[np.arange(n), b])
        scores.append(np.median(r[inliers] ** 2))
    return float(scores[1] / max(scores[0], 1e-12))


def _branch(residuals: NDArray) -> NDArray[np.int64]:
    """Per slice 0 (the network's branch) or 1 (its twin) from residuals ``[..., 2]``: the twin only
    when it is nearer by :data:`BRANCH_MARGIN_MM` (a slice near the mid-sagittal plane is its own
    twin within the error: then the network's pose stands)."""
    return (residuals[..., 1] + BRANCH_MARGIN_MM < residuals[..., 0]).astype(np.int64)


def _neighbour_noise2(chosen: NDArray, own: NDArray, inv_n: NDArray, t: NDArray, inliers: NDArray,
                      fallback: float) -> float:
    """Half the median squared E.D. between slices next to each other in acquisition time."""
    order = np.argsort(t)
    pairs = [(a, c) for a, c in zip(order[:-1], order[1:]) if inliers[a] and inliers[c]]
    if not pairs:
        return fallback
    a, c = np.array(pairs).T
    return float(np.median(ed(chosen[a] @ inv_n[c], own[c]) ** 2)) / 2.0


def _loo_weights(t: NDArray, bandwidth: float, w: NDArray) -> NDArray:
    """``[n, n]`` leave-one-out weights: a Gaussian kernel over acquisition time times the robust weights."""
    dt = t[:, None] - t[None]
    kern = np.ones(dt.shape) if np.isinf(bandwidth) else np.exp(-0.5 * (dt / bandwidth) ** 2)
    wts = kern * w[None]
    np.fill_diagonal(wts, 0.0)
    return wts


def _local_models(chosen: NDArray, centre: NDArray, weights: NDArray) -> NDArray:
    """Weighted means ``[..., n, 4, 4]`` of the proposals ``chosen [n, 4, 4]`` with rows of ``weights [..., n, n]``.

    Linearised at ``centre`` (rotation vectors of ``R_c^T R_j``, translations as they are): the
    proposals of one stack lie within the motion's few tens of degrees of each other, where this
    matches the Fréchet mean to a small fraction of a degree, and it is one matrix product for all
    slices and kernels. Rows with no weight fall back to ``centre``.
    """
    rc = centre[:3, :3]
    omega = se3.so3_log(rc.T @ chosen[:, :3, :3])                           # [n, 3]
    total = weights.sum(axis=-1, keepdims=True)
    norm = np.where(total > 0, weights / np.where(total > 0, total, 1.0), 0.0)
    w_omega = norm @ omega
    w_t = np.where(total > 0, norm @ chosen[:, :3, 3], centre[:3, 3])
    return make_pose(rc @ se3.so3_exp(w_omega), w_t)


def _scale(r: NDArray) -> float:
    """Robust scale of non-negative residuals ``r``: ``1.4826 median(r)`` (a standard deviation for
    half-normal residuals), floored at :data:`MIN_SCALE_MM`."""
    if len(r) == 0:
        return MIN_SCALE_MM
    return float(max(se3.MAD_SCALE * np.median(r), MIN_SCALE_MM))


def _tukey(r: NDArray, scale: float) -> NDArray:
    u = r / (TUKEY_C * scale)
    return np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0)
