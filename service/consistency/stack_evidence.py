"""What the stack stage finds of one stack before the request has a say: steps 1 to 3 of
:mod:`service.consistency.stack_fit` (each slice's branch by RANSAC, the robust rigid fit, the motion
model) and the stack's own branch margin. None of it depends on the request's other stacks, so a
stack fitted again with their placement (:func:`~service.consistency.stack_fit.fit_stack`'s
``reference``) starts from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.consistency.error_shape import anatomical_axes, relative_depth
from service.consistency.motion_model import ERROR_CORRELATIONS, NO_VOTE, Grid, MotionFit, fit_motion
from service.consistency.slice_order import acquisition_orders
from service.consistency.slice_weights import MIN_NOISE_MM, noise_scales, precisions, robust_weights
from service.consistency.slice_weights import votes as slice_votes
from service.geometry import se3, twin
from service.geometry.anchors import ed
from service.geometry.pose import make_pose, translate

RANSAC_TAU_MM = 30.0
"""MSAC truncation of a slice's residual when scoring branch proposals (mm of E.D.)."""
MIN_SLICES = 3
IRLS_ROUNDS = 6
MEAN_TOL_RAD = 1e-7
"""Fréchet-mean tolerance of the stage (1e-7 rad moves an anchor 60 mm away by 6 nm)."""
BRANCH_MARGIN_MM = 5.0
FIRST_GRID = Grid(error_correlations=(0.5,))
"""The first motion fit only re-weighs the slices: one error correlation suffices."""


@dataclass(frozen=True)
class StackEvidence:
    """What :func:`stack_evidence` finds of a stack, the same whatever the request's other stacks say.
    ``motion`` is None where too few slices may vote or none keeps a weight (the stack is then
    returned as the network gave it); the fields after ``use`` are then None too."""

    poses: NDArray[np.float64]
    origin: NDArray[np.float64]
    to_scanner: NDArray[np.float64]
    use: NDArray[np.bool_]
    cand: NDArray[np.float64] | None = None             # [n, 2, 4, 4]: each pose and its twin
    proposals: NDArray[np.float64] | None = None        # [n, 2, 4, 4]: the stack placement each implies
    inv_n: NDArray[np.float64] | None = None
    sig: NDArray[np.float64] | None = None              # each slice's noise scale (mm)
    rigid: NDArray[np.float64] | None = None            # the robust rigid placement
    weights: NDArray[np.float64] | None = None
    inliers: NDArray[np.bool_] | None = None
    orders: dict[str, NDArray] | None = None
    centre: NDArray[np.float64] | None = None
    shape: dict | None = None                           # the motion model's error shape arguments
    votes: NDArray[np.float64] | None = None
    grid: Grid | None = None
    motion: MotionFit | None = None
    first_branch: NDArray[np.int64] | None = None       # by the rigid fit, which the motion model was fitted on
    branch: NDArray[np.int64] | None = None             # by the motion model's leave-one-out prediction
    margin: float = float("nan")                        # the stack's own branch margin
    memo: dict | None = None                            # the motion model's eigendecompositions


def stack_evidence(poses: ArrayLike, network_from_scanner: ArrayLike, usable: ArrayLike | None = None,
                   plane_x_mm: float = twin.DEFAULT_PLANE_X_MM, expected_error_mm: ArrayLike | None = None,
                   times: dict[str, NDArray] | None = None, error_shape: ArrayLike | None = None,
                   depth_gain: float = 0.0, error_correlations: tuple[float, ...] = ERROR_CORRELATIONS) -> StackEvidence:
    """What :func:`~service.consistency.stack_fit.fit_stack` finds of one stack before the request has a
    say (the arguments are that function's): the slices' branches by RANSAC, the robust rigid fit, the
    motion model and the stack's own branch margin.

    Example (12 slices, half of them on their twin, decided by the stack itself):
        >>> from service.geometry import se3
        >>> n = np.stack([se3.exp(np.array([0, 0, 0, 0, 0, -3.0 * k])) for k in range(12)])
        >>> truth = se3.exp(np.array([0.3, -0.2, 0.4, 5.0, -2.0, 1.0])) @ se3.inverse(n)
        >>> poses = truth.copy(); poses[::2] = twin.twin(truth[::2])
        >>> found = stack_evidence(poses, n)
        >>> found.branch.tolist() == [1, 0] * 6, found.margin > 1.5, stack_evidence(poses[:2], n[:2]).motion
        (True, True, None)
    """
    p = np.asarray(poses, dtype=np.float64)
    # the fit's frame is the scanner's moved to the slices' centre: means of rigid maps (a rotation
    # with a translation) depend on the point they turn about, and the scanner's origin (its table
    # position) lies anywhere, often far from the fetus; from this point on, the fit sees none of it
    origin = se3.inverse(np.asarray(network_from_scanner, dtype=np.float64))[:, :3, 3].mean(axis=0)
    nk = np.asarray(network_from_scanner, dtype=np.float64) @ translate(origin)
    to_scanner = translate(-origin)         # atlas_from_fit_frame @ to_scanner: atlas_from_scanner
    n = len(p)
    use = np.ones(n, bool) if usable is None else np.asarray(usable, bool).copy()
    if use.sum() < MIN_SLICES:
        return StackEvidence(p, origin, to_scanner, use)
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

    # 2. rigid fit: IRLS with Tukey weights (on residuals in units of each slice's expected error,
    #    and times its precision, when the errors are known), branches re-decided each round
    sig = None if expected_error_mm is None else noise_scales(expected_error_mm, use)
    s = proposals[idx[h], b]
    for _ in range(IRLS_ROUNDS):
        model = s @ inv_n                                                   # [n, 4, 4]
        both = ed(model[:, None], cand)                                     # [n, 2]
        branch = _branch(both)
        r = both[np.arange(n), branch]
        tukey = robust_weights(r, sig, use)
        w = tukey * (1.0 if sig is None else precisions(sig, use))
        if w.sum() <= 0:
            return StackEvidence(p, origin, to_scanner, use)
        s = _local_models(proposals[np.arange(n), branch], s, w[None])[0]   # one Gauss-Newton step a round
    inliers = (w > 0) & use

    # 3. motion: a Gaussian process over acquisition time (service/consistency/motion_model.py);
    #    then the branches against what the other slices predict (the rigid fit is off by the
    #    motion; near the mid-sagittal plane that can exceed half the distance to the twin); then
    #    the stack's branch as a whole by the rigid model (only the order along the normal tells a
    #    stack from its twin, and a flexible motion model can bend to either order)
    orders = acquisition_orders(n) if times is None else times
    centre = inv_n[:, :3, 3].mean(axis=0)                                   # the slices' centre (0 in the fit's frame)
    axes = inv_n[idx[0], :3, :3]                                            # the stack's x, y, normal in scanner
    axes = axes @ anatomical_axes(s[:3, :3] @ axes)                         # x along the brain's left-right
    # the slices' offsets from the centre along the normal (their in-plane offsets, a few mm, left out:
    # then only the two in-plane translations vary from slice to slice, and the other four share
    # one eigendecomposition in the motion model; the poses come out the same to a hundredth of a mm)
    along = ((inv_n[:, :3, 3] - centre) @ axes) * [0.0, 0.0, 1.0]
    grow = 1.0 + depth_gain * relative_depth(along[:, 2], use) ** 2
    shape = {"axes": axes} if error_shape is None else {   # errors per coordinate about each slice's origin
        "axes": axes, "noise_shape": np.asarray(error_shape, dtype=np.float64)[None] * grow[:, None],
        "lever_mm": along[:, 2]}
    on = np.arange(n)
    own, chosen = cand[on, branch], proposals[on, branch]                   # each slice on its branch
    if sig is None:
        noise2 = _neighbour_noise2(chosen, own, inv_n, on, inliers, float(np.median(r[inliers] ** 2)))
        sig = np.full(n, np.sqrt(max(noise2, MIN_NOISE_MM ** 2)))
    votes = np.where(inliers, sig / np.sqrt(np.maximum(tukey, 1e-12)), NO_VOTE)
    grid = Grid(error_correlations=tuple(error_correlations))
    first = FIRST_GRID if set(FIRST_GRID.error_correlations) <= set(error_correlations) else Grid(
        error_correlations=grid.error_correlations[:1])             # the first fit only re-weighs: one correlation
    motion = fit_motion(chosen, s, votes, orders, centre, first, **shape)
    # a slice far from the rigid fit may just have moved: every usable slice is weighed again by
    # how well the others predict it, in units of the spread both errors explain
    votes = slice_votes(ed(motion.loo @ inv_n, own), motion, sig, use)
    memo: dict = {}                        # the final fit reuses this one's eigendecompositions where its votes are these
    motion = fit_motion(chosen, s, votes, orders, centre, grid, memo=memo, **shape)
    decided = _branch(ed((motion.loo @ inv_n)[:, None], cand))
    return StackEvidence(p, origin, to_scanner, use, cand, proposals, inv_n, sig, s, w, inliers, orders, centre, shape,
                         votes, grid, motion, branch, decided, _branch_margin(proposals, cand, decided, inv_n, w, inliers),
                         memo)


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
