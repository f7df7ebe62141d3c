"""The stack-consistency stage of ``/v1/predict``: per stack, the network's poses in, consistent poses out.

The stage sits between inference (with its twin-aware MC statistics) and the response. It needs,
per slice, the map from the stack's scanner frame to the slice's network frame; the pipeline
composes it once here from the service's own crop/centre and the file's geometry::

    network_from_scanner_k = network_from_input_k @ slice_from_voxel_k @ voxel_from_scanner
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.consistency.cross_stack import pool_stacks
from service.consistency.mirrored_stacks import mirrored_stacks
from service.consistency.stack_evidence import StackEvidence
from service.consistency.stack_fit import StackFit, fit_stack
from service.geometry import se3
from service.geometry.pose import translate


@dataclass
class Pooled:
    """Where pooling the request's stacks put one stack (:func:`pool_request`)."""

    atlas_from_scanner: NDArray[np.float64]   # 4 x 4, the stack's pooled placement
    stacks: int                               # stacks pooled
    between_stacks_sd_mm: float               # spread of the placements between stacks
    placement_sd_mm: float = float("nan")     # standard error of the pooled placement per coordinate


@dataclass
class ImageConsistency:
    """What refining the poses where slices of different stacks cross did to one stack."""

    stacks: int                               # stacks refined together
    pairs: int                                # crossing pairs of slices used
    slices_refined: int
    median_move_mm: float
    mismatch_before: float                    # the image term per weighted point (NaN: none)
    mismatch_after: float
    slice_mismatch: NDArray[np.float64] | None = None       # [n] each slice's image term after, over the request's median (NaN: on no line)
    expected_before_mm: NDArray[np.float64] | None = None   # [n] each slice's expected E.D. before the refinement
    slice_spread_mm: NDArray[np.float64] | None = None      # [n] each refined slice's Laplace spread (NaN: not refined)
    placement_floor_mm: float = 0.0                         # no returned expected error lies below it (placement_floor_mm)


@dataclass
class StackPoses:
    """One stack's slices after the stage (or without it), and what the request's later steps did."""

    poses: NDArray[np.float64]          # [n, 4, 4] network frame -> atlas
    twin_mass: NDArray[np.float64]      # [n] MC mass on the other twin of the reported pose
    twinned: NDArray[np.bool_]          # [n] reported pose is the twin of the network's majority branch
    inconsistent: NDArray[np.bool_]     # [n]
    fit: StackFit | None                # None when the stage is off
    expected_error_mm: NDArray[np.float64] | None = None   # [n] expected E.D. of each pose (None: not calibrated)
    pooled: Pooled | None = None
    image_consistency: ImageConsistency | None = None
    apart_mm: float = float("nan")
    """How far the stack's brain lies from the request's fetus where it sees another
    (:func:`~service.preprocess.one_fetus.apart_from_fetus`; NaN: with it): the stack takes no part
    in the request's decisions, pooling or image stage, and none of its slices is accepted."""

    @property
    def apart(self) -> bool:
        """The stack's brain is not the request's fetus's (:attr:`apart_mm`)."""
        return bool(np.isfinite(self.apart_mm))

    def part(self, which: slice) -> "StackPoses":
        """The poses of the slices ``which`` alone (what a stream answers for one slice)."""
        expected = None if self.expected_error_mm is None else self.expected_error_mm[which]
        return StackPoses(self.poses[which], self.twin_mass[which], self.twinned[which], self.inconsistent[which],
                          None, expected)


def network_from_voxel(input_from_network: NDArray, slice_from_voxel: NDArray) -> NDArray[np.float64]:
    """``[n, 4, 4]`` voxel ``(i, j, k)`` of slice ``k`` -> its network frame (the service's crop/centre)."""
    return se3.inverse(input_from_network) @ slice_from_voxel


def consistent_poses(mean: NDArray, twin_mass: NDArray, network_from_vox: NDArray, scanner_from_voxel: NDArray,
                     usable: NDArray, plane_x_mm: float, expected_error_mm: NDArray | None = None,
                     enabled: bool = True, times: dict[str, NDArray] | None = None,
                     error_shape: NDArray | None = None, depth_gain: float = 0.0,
                     reference: NDArray | None = None, request_margin: float | None = None,
                     evidence: StackEvidence | None = None, keep_evidence: bool = False) -> StackPoses:
    """Run :func:`fit_stack` on one stack (or pass the network's poses through when ``enabled`` is False).

    ``expected_error_mm`` is each network pose's expected error: the MC spread times the model's
    calibration. The returned ``expected_error_mm`` is that of the returned poses: the stack model's
    posterior spread where the stack is decidable, the network poses' otherwise. ``times``: the candidate acquisition
    orders (:class:`~service.consistency.slice_order.SliceOrder`; default every named one).
    ``error_shape``, ``depth_gain``: the model's ``mc_error_shape`` and ``mc_error_depth_gain`` (see :func:`fit_stack`).
    ``reference``: the placement of the request's stacks that decided their branch (:func:`request_reference`);
    ``request_margin``: the stack's own branch margin under which that placement decides its branch;
    ``evidence``, ``keep_evidence``: where the stack is fitted again with these inputs, its first fit's
    ``evidence``, which that fit keeps where asked (see :func:`fit_stack`).
    """
    n = len(mean)
    if not enabled:
        return StackPoses(mean, twin_mass, np.zeros(n, bool), np.zeros(n, bool), None, expected_error_mm)
    network_from_scanner = network_from_vox @ np.linalg.inv(scanner_from_voxel)
    fit = fit_stack(mean, network_from_scanner, usable, plane_x_mm, expected_error_mm, times, error_shape, depth_gain,
                    reference, request_margin=request_margin, evidence=evidence, keep_evidence=keep_evidence)
    mass = np.where(fit.twinned, 1.0 - twin_mass, twin_mass)
    return StackPoses(fit.poses, mass, fit.twinned, fit.inconsistent, fit,
                      fit.expected_error_mm if fit.decidable else expected_error_mm)


def branch_set(out: StackPoses) -> bool:
    """The stage fitted one consistent stack and its left-right branch is set, by the stack's own
    slices or by the request's other stacks; otherwise (and for a stack the request took for
    mirrored, ``StackFit.mirrored``) each slice keeps the network's branch. A branch the request set
    is *known* only where the stack agrees with the request on it (``StackFit.branch_known``).

    Example:
        >>> from types import SimpleNamespace
        >>> fit = SimpleNamespace(decidable=True, branch_decided=False, branch_from_request=True, mirrored=False)
        >>> branch_set(SimpleNamespace(fit=fit)), branch_set(SimpleNamespace(fit=None))
        (True, False)
    """
    return (out.fit is not None and out.fit.decidable and (out.fit.branch_decided or out.fit.branch_from_request)
            and not out.fit.mirrored)


def undecided(out: StackPoses) -> bool:
    """The stage found one consistent stack but not its left-right branch, and the request has not
    decided it either (it may: a stack the other stacks overruled, :func:`checked_branch`, has been);
    a stack of another fetus (:attr:`StackPoses.apart`) is not the request's to decide."""
    return (out.fit is not None and out.fit.decidable and not out.fit.branch_decided and not out.fit.branch_from_request
            and not out.apart)


MISFIT_ONSET = 0.6
"""Where a stack's slices start to disagree with its motion model more than its spreads explain: the
median (root mean square) of their leave-one-out residuals in units of the spread both errors
explain (:attr:`~service.consistency.stack_fit.StackFit.residual_z`)."""
MISFIT_GAIN = 1.4
"""How fast a stack's expected errors grow past :data:`MISFIT_ONSET` (:func:`misfit_factor`). Onset
and gain are measured on simulated stacks sent alone (smooth, jumping and independent motion; the
calibration and its check in docs/reports/consistency-experiments.md)."""


def misfit_factor(fit: StackFit | None) -> float:
    """The factor on a stack's expected errors where no later stage weighs its slices again.

    The motion model's spreads hold where the fetus moves as the model says, smoothly. Where it
    jumps, or every slice moves on its own, the model's spreads are too small by up to half again
    (stacks sent alone: RMS E.D. / RMS expected 1.3-1.5), and its slices' residuals against what
    the others predict are larger than the spreads explain. The factor is
    ``1 + MISFIT_GAIN * max(0, z - MISFIT_ONSET)``, ``z`` the stack's median (RMS) residual in
    units of that spread over the slices that may vote (an empty slice's own pose is no
    measurement: its residual is NaN and counts for nothing); 1 for a stack the stage did not fit.

    Example (the same stack with and without two empty slices):
        >>> from types import SimpleNamespace
        >>> round(misfit_factor(SimpleNamespace(decidable=True, residual_z=np.array([0.5, 1.2, 1.0]))), 3)
        1.56
        >>> round(misfit_factor(SimpleNamespace(decidable=True, residual_z=np.array([0.5, 1.2, 1.0, np.nan, np.nan]))), 3)
        1.56
        >>> misfit_factor(None)
        1.0
    """
    z = None if fit is None or not fit.decidable else getattr(fit, "residual_z", None)
    z = np.asarray([] if z is None else z, np.float64)
    z = z[np.isfinite(z)]
    if len(z) == 0:
        return 1.0
    return 1.0 + MISFIT_GAIN * max(0.0, float(np.sqrt(np.median(z ** 2))) - MISFIT_ONSET)


CHECKED_MARGIN = 3.0
"""A stack that decided its branch by a margin under this is checked against the request's other
stacks (:func:`checked_branch`): a stack whose slices tell its branch only
weakly can land whole on its twin with confident slices (docs/consistency.md)."""
OVERRULE_MARGIN = 3.0
"""Such a stack takes the request's branch where, refitted, it lies on it within
:data:`~service.consistency.stack_fit.REQUEST_AGREEMENT_MM` of the other stacks and its own first
branch at least this many times as far: its slices' own decision is overruled on clear evidence only."""


def checked_branch(out: StackPoses, reference: NDArray | None,
                   refit: Callable[[NDArray, float], StackPoses]) -> StackPoses:
    """``out``, or the stack fitted again where the other stacks overrule its branch.

    A stack that decided its left-right branch by its own slices, but by less than
    :data:`CHECKED_MARGIN`, is fitted again (``refit(reference, CHECKED_MARGIN)``) with the other
    stacks' placement ``reference`` (:func:`request_reference` of the others) deciding. The refit is
    taken where it chose the other branch and sits where the other stacks do on it and far from
    them on its first one (``StackFit.agrees_by(OVERRULE_MARGIN)``); otherwise ``out`` stands, as does
    a stack of another fetus (:attr:`StackPoses.apart`).
    """
    fit = out.fit
    if reference is None or fit is None or out.apart or not fit.branch_decided or fit.branch_margin >= CHECKED_MARGIN:
        return out
    redo = refit(reference, CHECKED_MARGIN)
    flipped = redo.fit is not None and redo.fit.branch_margin < 1.0 and redo.fit.agrees_by(OVERRULE_MARGIN)
    return redo if flipped else out


def request_reference(outs: list[StackPoses]) -> NDArray[np.float64] | None:
    """Where the request's stacks that decided their left-right branch (of its fetus: not
    :attr:`StackPoses.apart`) put the scanner frame: their placements' mean, each weighed by its precision (None when no stack decided).

    The stacks of one request share the scanner frame; a stack that cannot tell its own branch (its
    slices' order along the normal fits its twin nearly as well) takes the branch nearer to this
    (:func:`fit_stack`'s ``reference``). The mean is taken about the stacks' centre, not the scanner's
    origin (a mean of rigid maps depends on the point they turn about), so where the files place the
    scanner's origin changes nothing."""
    fits = [o.fit for o in outs if o.fit is not None and o.fit.branch_decided and not o.fit.mirrored and not o.apart
            and o.fit.atlas_from_scanner is not None and o.fit.centre is not None and np.isfinite(o.fit.placement_sd_mm)]
    if not fits:
        return None
    weights = np.array([1.0 / max(f.placement_sd_mm, 1e-3) ** 2 for f in fits])
    centre = np.mean([f.centre for f in fits], axis=0)
    about = np.stack([f.atlas_from_scanner for f in fits]) @ translate(centre)
    return se3.frechet_mean(about, weights) @ translate(-centre)


def mark_mirrored(outs: list[StackPoses], scanner_from_voxel: list[NDArray]) -> list[int]:
    """Mark the stacks whose voxels the request finds mirrored against their file's header
    (:func:`~service.consistency.mirrored_stacks.mirrored_stacks` of the stacks of its fetus that
    decided their branch by their own slices), in place: ``StackFit.mirrored``, and every slice inconsistent (none
    is accepted: each lies on the twin of where the others put it, or its stack cannot be told from
    its mirror-image partner). Returns their indices.

    ``scanner_from_voxel``: each stack's affine.
    """
    placements = [o.fit.atlas_from_scanner if o.fit is not None and o.fit.branch_decided and not o.apart else None
                  for o in outs]
    flagged = mirrored_stacks(placements, [np.asarray(a)[:3, :3] for a in scanner_from_voxel])
    for out, mirrored in zip(outs, flagged):
        if mirrored:
            out.fit.mirrored = True
            out.inconsistent = np.ones(len(out.poses), bool)
    return [i for i, m in enumerate(flagged) if m]


def pool_request(outs: list[StackPoses]) -> None:
    """Pool the placements of a request's stacks (:mod:`service.consistency.cross_stack`), in place.

    Only stacks whose left-right branch is known take part: decided by their own slices, or by the
    request where they agree with it (``StackFit.branch_known``; a stack that may be the mirror image
    of the others would only add spread), and whose brain is the request's fetus's (not
    :attr:`StackPoses.apart`). A stack's placement is where its motion model puts it on
    average over its acquisition (not its robust rigid fit, which sits off that mean where the fetus
    moved, and would pool a position the stack never had). Each such
    stack's poses move with its pooled placement, and their ``expected_error_mm`` follows
    (:func:`pooled_expected_error_mm`); its ``pooled`` says where it went."""
    which = [i for i, o in enumerate(outs) if o.fit is not None and o.fit.branch_known and not o.apart
             and o.fit.centre is not None
             and o.fit.atlas_from_scanner is not None and np.isfinite(o.fit.placement_sd_mm)]
    if len(which) < 2:
        return
    fits = [outs[i].fit for i in which]
    pooled = pool_stacks(np.stack([f.atlas_from_scanner for f in fits]), np.array([f.placement_sd_mm for f in fits]),
                         np.stack([f.centre for f in fits]))
    for j, i in enumerate(which):
        out, fit = outs[i], fits[j]
        out.poses = pooled.corrections[j] @ out.poses
        if out.expected_error_mm is not None and fit.placement_cov is not None:
            out.expected_error_mm = pooled_expected_error_mm(out.expected_error_mm, fit.placement_cov,
                                                             fit.placement_sd_mm ** 2, float(pooled.sd_mm[j] ** 2),
                                                             float(pooled.kept[j]))
        out.pooled = Pooled(pooled.corrections[j] @ fit.atlas_from_scanner, len(which), float(pooled.tau_mm),
                            float(pooled.sd_mm[j]))


def pooled_expected_error_mm(expected_error_mm: NDArray, cov: NDArray, v: float, v_pooled: float, kept: float) -> NDArray:
    """Each slice's expected E.D. once its stack moved to its pooled placement.

    A slice's error ``e_k`` moves by the placement's correction, ``(1 - kept)`` of the pooled
    placement's error less the stack's own ``e_s`` (variance ``v`` per coordinate, covariance
    ``cov_k`` with ``e_k``). With one position shared (``kept = 0``) the pooled error has
    covariance ``v_pooled`` with ``e_s`` and ``cov_k v_pooled / v`` with ``e_k``, so per coordinate
    ``var(e_k') = var(e_k) + v_pooled - v + 2 (v - cov_k)(1 - v_pooled / v)``; a stack that keeps part
    of its own position changes by that share less. A slice whose error is its stack's (``cov_k = v``)
    loses ``v - v_pooled``; one whose error is its own gains the placement's correction.

    Example:
        >>> pooled_expected_error_mm(np.array([3.0]), np.array([2.0]), 2.0, 0.5, 0.0).round(3).tolist()   # 9 - 3 * 1.5
        [2.121]
    """
    change = v_pooled - v + 2.0 * (v - np.asarray(cov)) * (1.0 - v_pooled / max(v, 1e-12))
    return np.sqrt(np.maximum(np.asarray(expected_error_mm) ** 2 + 3.0 * (1.0 - kept) * change, 0.0))
