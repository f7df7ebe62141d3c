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

from service.consistency.motion_model import ERROR_CORRELATIONS, NO_VOTE, fit_motion, refit
from service.consistency.stack_evidence import MEAN_TOL_RAD, StackEvidence, stack_evidence
from service.geometry import se3, twin
from service.geometry.anchors import ed
from service.geometry.pose import translate

MIN_INLIER_FRACTION = 0.5
"""A stack whose model explains fewer of its usable slices than this is undecidable."""
MAX_MODEL_ERROR_MM = 25.0
"""A stack whose model predicts its slices worse than this (the spread of the others' prediction)
has no common geometry (e.g. every slice moved independently): undecidable, nothing is changed."""
OUTLIER_K = 3.0
OUTLIER_FLOOR_MM = 15.0
"""A slice is inconsistent when its residual to the model exceeds ``max(K * sqrt(network^2 +
model^2), floor)``: K times what the two estimated errors together explain."""
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
        evidence: what the fit found before the request had a say
            (:class:`~service.consistency.stack_evidence.StackEvidence`; only with ``keep_evidence``): the
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


def fit_stack(poses: ArrayLike, network_from_scanner: ArrayLike, usable: ArrayLike | None = None,
              plane_x_mm: float = twin.DEFAULT_PLANE_X_MM, expected_error_mm: ArrayLike | None = None,
              times: dict[str, NDArray] | None = None, error_shape: ArrayLike | None = None,
              depth_gain: float = 0.0, reference: ArrayLike | None = None,
              error_correlations: tuple[float, ...] = ERROR_CORRELATIONS,
              request_margin: float | None = None, evidence: StackEvidence | None = None,
              keep_evidence: bool = False) -> StackFit:
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
        evidence: the stack's :func:`~service.consistency.stack_evidence.stack_evidence` of these
            arguments, where the stack is fitted again with another ``reference``: the same fit as from
            the arguments, without their work done again.
        keep_evidence: return that evidence on the fit (:attr:`StackFit.evidence`; it holds the motion
            model's eigendecompositions, megabytes for a long stack: kept only where it is used).
    """
    found = evidence if evidence is not None else stack_evidence(poses, network_from_scanner, usable, plane_x_mm,
                                                                  expected_error_mm, times, error_shape, depth_gain,
                                                                  error_correlations)
    kept = found if keep_evidence else None
    p, origin, to_scanner, use, n = found.poses, found.origin, found.to_scanner, found.use, len(found.poses)
    if found.motion is None:
        return StackFit(p.copy(), np.zeros(n, bool), np.zeros(n, bool), np.full(n, np.nan), False, evidence=kept)
    cand, proposals, inv_n, sig, s, w, inliers = found.cand, found.proposals, found.inv_n, found.sig, found.rigid, found.weights, found.inliers
    orders, centre, shape, votes, grid, motion = found.orders, found.centre, found.shape, found.votes, found.grid, found.motion
    first, branch, margin, memo = found.first_branch, found.branch, found.margin, dict(found.memo)
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
                        motion.order, motion.length, network_mm, model_mm, evidence=kept)
    final_votes = np.where(use & ~inconsistent, np.where(np.isfinite(votes), votes, sig), NO_VOTE)
    final = fit_motion(chosen, s, final_votes, orders, centre, grid, memo=memo, **shape)   # every model again, averaged
    return StackFit(final.poses @ inv_n, branch == 1, inconsistent, r_loo, True, final.placement @ to_scanner, fraction,
                    final.order, final.length, network_mm, model_mm, margin, final.sd_mm, final.placement_sd_mm,
                    centre + origin, final.placement_cov, by_request, (far[0], far[1]) if by_request else (np.nan, np.nan),
                    np.where(use, r_loo / np.sqrt(noise_sd ** 2 + motion.model_sd_mm ** 2), np.nan), evidence=kept)
