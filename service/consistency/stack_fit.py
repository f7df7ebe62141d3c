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
3. **Motion** (a Gaussian process over acquisition time, :mod:`service.consistency.motion_model`):
   the proposals, each with its expected error (its calibrated MC spread, or without one an
   estimate from neighbouring slices), follow a smooth motion; the acquisition order (sequential
   or interleaved), the motion's length (down to rigid) and amplitude, and how much neighbouring
   slices' network errors are alike, are chosen by the marginal likelihood.
4. **Fusion and consistency**: a slice whose own pose disagrees with the others' prediction
   beyond what both spreads explain is *inconsistent*: it does not vote and takes the prediction;
   with the remaining votes every motion model is fitted again, and each slice's pose becomes the
   posterior mean averaged over the models (its own proposal weighed against the others' by their
   errors). When fewer than :data:`MIN_INLIER_FRACTION` of the slices agree, or
   the model's spread exceeds :data:`MAX_MODEL_ERROR_MM`, the stack is *undecidable* and nothing
   is changed.

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

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.consistency.error_shape import anatomical_axes, relative_depth
from service.consistency.motion_model import ERROR_CORRELATIONS, NO_VOTE, Grid, MotionFit, fit_motion, refit
from service.consistency.slice_order import acquisition_orders
from service.consistency.slice_weights import MIN_NOISE_MM, noise_scales, precisions, robust_weights
from service.consistency.slice_weights import votes as slice_votes
from service.geometry import se3, twin
from service.geometry.anchors import ed
from service.geometry.pose import make_pose, translate

RANSAC_TAU_MM = 30.0
"""MSAC truncation of a slice's residual when scoring branch proposals (mm of E.D.)."""
MIN_INLIER_FRACTION = 0.5
"""A stack whose model explains fewer of its usable slices than this is undecidable."""
MAX_MODEL_ERROR_MM = 25.0
"""A stack whose model predicts its slices worse than this (the spread of the others' prediction)
has no common geometry (e.g. every slice moved independently): undecidable, nothing is changed."""
MIN_SLICES = 3
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
REQUEST_AGREEMENT_MM = 15.0
"""A stack whose branch the request decided agrees with the request where its rigid fit on that branch
lies within this mean E.D. of the request's reference (the fetus's move between two stacks) and its
twin at least :data:`REQUEST_MARGIN` times as far; a stack that fits the request on neither branch
(a mask that runs on into the fetal body) does not."""
REQUEST_MARGIN = 1.25
"""A stack near the mid-sagittal plane has a twin placement close to its own (a real sagittal stack
lies about as far from the request on its twin as on its branch), so a small margin lets it agree
with the request and keeps a change of its voxels below the file's rounding from parting them
(docs/reports/consistency-experiments.md). A branch the stack decided itself is overruled only on
more (``stage.OVERRULE_MARGIN``)."""
FIRST_GRID = Grid(error_correlations=(0.5,))
"""The first motion fit only re-weighs the slices: one error correlation suffices."""


@dataclass
class StackFit:
    """What the stage decided for one stack.

    Attributes:
        poses: ``[n, 4, 4]`` the consistent poses (network frame -> atlas).
        twinned: ``[n]`` slices whose pose is the twin of the network's.
        inconsistent: ``[n]`` slices whose own pose disagreed with the stack model.
        residual_mm: ``[n]`` E.D. between the network's pose (on its branch) and the model's.
        decidable: False where the slices do not agree on one stack (nothing was changed).
        atlas_from_scanner: ``4 x 4`` the stack's placement: where its slices were on average over
            the acquisition (the robust rigid fit moved by the mean of the fitted motion; the rigid
            fit alone where undecidable, not reported).
        inlier_fraction: fraction of usable slices the stack model explains (not inconsistent).
        acquisition_order: the order chosen (``sequential``, ``interleaved-even-first``, ...).
        bandwidth: length of the motion model in acquisitions (``inf``: rigid, no motion needed).
        noise_mm, model_mm: estimated E.D. of a network pose and of the model's prediction.
        branch_margin: how many times worse the whole stack on its other twin fits one rigid
            stack (under :data:`MIN_STACK_BRANCH_MARGIN`: this stack does not decide its branch).
        expected_error_mm: ``[n]`` expected E.D. of each returned pose: the motion model's posterior
            spread, the rigid fit's own included (``None`` when undecidable).
        placement_sd_mm: standard error of ``atlas_from_scanner`` per coordinate (mm: translations,
            and rotation vectors times :data:`~service.geometry.anchors.ANCHOR_HALF_SIZE_MM`).
        centre: ``[3]`` the stack's centre in scanner mm (its rotations are linearised about it).
        placement_cov: ``[n]`` covariance of each slice's error with the placement's (mm^2 per coordinate).
        branch_from_request: the branch was not decided by this stack but by the request's other
            stacks (the ``reference`` of :func:`fit_stack`).
        request_distance_mm: with ``branch_from_request``, the mean E.D. of the stack's rigid fit on
            the branch taken, and on the other, from the reference (``[taken, other]``).
        residual_z: ``[n]`` each slice's ``residual_mm`` in units of the spread that the network's error
            and the others' prediction explain (the measure of :data:`OUTLIER_K`; NaN for a slice that
            may not vote, whose own pose is no measurement: an empty slice; None when undecidable).
        mirrored: the request's other stacks hold the fetus where this stack, reflected, does: its
            voxels are the mirror image of what its file says
            (:func:`~service.consistency.mirrored_stacks.mirrored_stacks`); its branch is not known.
        evidence: what the fit found before the request had a say (:class:`StackEvidence`): the
            start of a fit of the same stack with another ``reference``.
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
    expected_error_mm: NDArray[np.float64] | None = None
    placement_sd_mm: float = float("nan")
    centre: NDArray[np.float64] | None = None
    placement_cov: NDArray[np.float64] | None = None
    branch_from_request: bool = False
    request_distance_mm: tuple[float, float] = (float("nan"), float("nan"))
    residual_z: NDArray[np.float64] | None = None
    mirrored: bool = False
    evidence: "StackEvidence | None" = field(default=None, repr=False, compare=False)

    @property
    def branch_decided(self) -> bool:
        """The stack's left-right branch is decided by its slices' order along the normal."""
        return bool(self.decidable and self.branch_margin >= MIN_STACK_BRANCH_MARGIN)

    @property
    def agrees_with_request(self) -> bool:
        """The request decided the stack's branch, and the stack sits where the request's stacks do on
        it and further from them on its twin (:data:`REQUEST_AGREEMENT_MM`, :data:`REQUEST_MARGIN`)."""
        return self.agrees_by(REQUEST_MARGIN)

    def agrees_by(self, margin: float) -> bool:
        """:attr:`agrees_with_request` with its twin at least ``margin`` times as far from the request
        as its branch (a stack's own decision overruled asks more: ``stage.OVERRULE_MARGIN``)."""
        taken, other = self.request_distance_mm
        return bool(self.decidable and self.branch_from_request and taken <= REQUEST_AGREEMENT_MM
                    and other >= margin * taken)

    @property
    def branch_known(self) -> bool:
        """The branch is decided by the stack itself, or by the request with the stack agreeing, and
        the stack is not the mirror image of the request's others (:attr:`mirrored`)."""
        return (self.branch_decided or self.agrees_with_request) and not self.mirrored


@dataclass(frozen=True)
class StackEvidence:
    """What :func:`stack_evidence` finds of a stack, the same whatever the request's other stacks say:
    a stack fitted again with their placement (:func:`fit_stack`'s ``reference``) starts from it.
    ``motion`` is None where too few slices may vote or none keeps a weight (the stack is then
    returned as the network gave it); the rest is then None too."""

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
    """What :func:`fit_stack` finds of one stack before the request has a say (its arguments, which this
    takes, are described there): the slices' branches by RANSAC, the robust rigid fit, the motion
    model and the stack's own branch margin (steps 1 to 3 of the module docstring)."""
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


def fit_stack(poses: ArrayLike, network_from_scanner: ArrayLike, usable: ArrayLike | None = None,
              plane_x_mm: float = twin.DEFAULT_PLANE_X_MM, expected_error_mm: ArrayLike | None = None,
              times: dict[str, NDArray] | None = None, error_shape: ArrayLike | None = None,
              depth_gain: float = 0.0, reference: ArrayLike | None = None,
              error_correlations: tuple[float, ...] = ERROR_CORRELATIONS,
              request_margin: float | None = None, evidence: StackEvidence | None = None) -> StackFit:
    """Make one stack's slice poses consistent (see the module docstring).

    Args:
        poses: ``[n, 4, 4]`` the network's poses (each on its MC-majority branch).
        network_from_scanner: ``[n, 4, 4]`` rigid maps from the scanner (stack) frame to each
            slice's network frame.
        usable: ``[n]`` slices allowed to vote (default all); the others only receive the model's pose.
        plane_x_mm: the atlas mid-sagittal plane of the twin.
        expected_error_mm: ``[n]`` the expected E.D. of each network pose (its calibrated MC spread). Motion
            that is independent from slice to slice cannot be told from network error by the poses
            alone; this tells them apart. Without it the error is estimated from acquisition
            neighbours (an upper bound: right for smooth motion, too trusting of the model for
            jittery motion).
        times: candidate acquisition times ``{order: [n]}`` of the slices (default: every named
            order, :func:`~service.consistency.slice_order.acquisition_orders`; see
            :class:`~service.consistency.slice_order.SliceOrder` for an order the user gave).
        error_shape: ``[6]`` the network's error variance per coordinate of its own frame (rotation
            about x, y, normal; translation along x, y, normal), mean 1: the model's
            ``mc_error_shape`` (:func:`~service.consistency.error_shape.error_shape`), about each
            slice's origin, whose offset along the normal couples a tilt with a shift of the stack's
            centre (:mod:`~service.consistency.motion_blocks`). Default: the coordinates about the
            stack's centre alike.
        depth_gain: ``beta``: the errors' variances grow by ``1 + beta rho^2`` beyond their
            expected errors towards the stack's outer slices (``rho`` the relative depth among
            the usable slices; the model's ``mc_error_depth_gain``,
            :func:`~service.consistency.error_shape.depth_gain`). Only with ``error_shape``.
        reference: ``4 x 4`` an ``atlas_from_scanner`` of the same scanner frame from stacks that
            decided their branch (:func:`~service.consistency.stage.request_reference`): where this
            stack does not decide its own (``branch_margin`` under :data:`MIN_STACK_BRANCH_MARGIN`),
            the branch whose rigid fit lies nearer to it is taken (``branch_from_request``). The
            whole stack's twin is a gross move (the mirror composed with the reversal of the slice
            order: 180 deg for a stack across the mid-sagittal plane), far beyond the fetus's usual
            motion between stacks.
        request_margin: with ``reference``, the request decides the branch wherever the stack's own
            margin is under this (None: :data:`MIN_STACK_BRANCH_MARGIN`, where the stack does not
            decide it); a larger one lets the other stacks overrule a stack that decided by a small margin.
        evidence: the stack's :func:`stack_evidence` of these arguments (a fit's own
            :attr:`StackFit.evidence`), where the stack is fitted again with another ``reference``: the
            same fit as from the arguments, without their work done again.
    """
    ev = evidence if evidence is not None else stack_evidence(poses, network_from_scanner, usable, plane_x_mm,
                                                               expected_error_mm, times, error_shape, depth_gain,
                                                               error_correlations)
    p, origin, to_scanner, use, n = ev.poses, ev.origin, ev.to_scanner, ev.use, len(ev.poses)
    if ev.motion is None:
        return StackFit(p.copy(), np.zeros(n, bool), np.zeros(n, bool), np.full(n, np.nan), False, evidence=ev)
    cand, proposals, inv_n, sig, s, w, inliers = ev.cand, ev.proposals, ev.inv_n, ev.sig, ev.rigid, ev.weights, ev.inliers
    orders, centre, shape, votes, grid, motion = ev.orders, ev.centre, ev.shape, ev.votes, ev.grid, ev.motion
    first, branch, margin, memo = ev.first_branch, ev.branch, ev.margin, dict(ev.memo)
    on = np.arange(n)
    own, chosen = cand[on, first], proposals[on, first]
    asked = MIN_STACK_BRANCH_MARGIN if request_margin is None else request_margin
    by_request = reference is not None and 1.0 / asked < margin < asked
    if by_request:                         # the request's other stacks decide: the branch nearer to them
        fits = [se3.frechet_mean(proposals[on, b], np.maximum(w, 1e-12), tol=MEAN_TOL_RAD) for b in (branch, 1 - branch)]
        ref = np.asarray(reference, dtype=np.float64) @ translate(origin)
        far = [float(ed(f @ inv_n[use], ref @ inv_n[use]).mean()) for f in fits]
        if far[1] < far[0]:
            branch, margin, s, far = 1 - branch, 1.0 / margin, fits[1], far[::-1]
    elif margin < 1.0:                     # the whole stack's twin is the better rigid stack: take it
        branch, margin = 1 - branch, 1.0 / max(margin, 1e-12)
        s = se3.frechet_mean(proposals[on, branch], np.maximum(w, 1e-12), tol=MEAN_TOL_RAD)
    if not np.array_equal(branch, first):
        own, chosen = cand[on, branch], proposals[on, branch]
        motion = refit(motion, chosen, s, votes, orders, centre, **shape)
    r_loo = ed(motion.loo @ inv_n, own)

    # 4. consistency: a slice the others predict worse than both errors explain is inconsistent and
    #    does not vote in the final model; every slice takes the model's posterior mean (its own
    #    pose weighed against its neighbours' by their errors; the prediction alone when it did not vote)
    noise_sd = motion.noise_scale * sig                                     # as the likelihood scaled them
    network_mm = float(np.sqrt(np.median(noise_sd[inliers] ** 2)))
    model_mm = float(np.sqrt(np.median(motion.model_sd_mm[use] ** 2)))
    limit = np.maximum(OUTLIER_K * np.sqrt(noise_sd ** 2 + motion.model_sd_mm ** 2), OUTLIER_FLOOR_MM)
    inconsistent = use & (r_loo > limit)
    fraction = float((use & ~inconsistent).sum() / use.sum())
    if fraction < MIN_INLIER_FRACTION or model_mm > MAX_MODEL_ERROR_MM:
        return StackFit(p.copy(), np.zeros(n, bool), np.zeros(n, bool), r_loo, False, s @ to_scanner, fraction,
                        motion.order, motion.length, network_mm, model_mm, evidence=ev)
    final_votes = np.where(use & ~inconsistent, np.where(np.isfinite(votes), votes, sig), NO_VOTE)
    final = fit_motion(chosen, s, final_votes, orders, centre, grid, memo=memo, **shape)   # every model again, averaged
    return StackFit(final.poses @ inv_n, branch == 1, inconsistent, r_loo, True, final.placement @ to_scanner, fraction,
                    final.order, final.length, network_mm, model_mm, margin, final.sd_mm, final.placement_sd_mm,
                    centre + origin, final.placement_cov, by_request, (far[0], far[1]) if by_request else (np.nan, np.nan),
                    np.where(use, r_loo / np.sqrt(noise_sd ** 2 + motion.model_sd_mm ** 2), np.nan), evidence=ev)


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
