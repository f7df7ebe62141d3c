"""The prediction pipeline of one request: prepared stacks -> poses -> accept flags.

Stages follow the paper's Fig. 1: localisation (uploaded mask, else the learned localiser of
:mod:`service.preprocess.localise`), N4 bias correction, masking and per-slice
rescale/crop/centre (:mod:`service.pipeline.prepare`), then here MC-dropout
inference of ALL slices of ALL stacks in one batched estimator call, twin-aware SE(3) statistics,
stack consistency (:mod:`service.consistency`), acceptance. The results are plain data
(:class:`StackPrediction`); :mod:`service.pipeline.documents` writes them as the contract's JSON.

Geometry of every slice (the composition is written once, in
:func:`service.consistency.stage.network_from_voxel`)::

    atlas_from_voxel = pose @ network_from_input @ input_from_voxel
                     = pose @ translate(-centroid) @ slice_from_voxel
"""

from __future__ import annotations

import hashlib
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import pairwise

import numpy as np
from numpy.typing import NDArray

from service.consistency.frame_error import frame_error_mm, request_network_error_mm
from service.consistency.slice_order import FROM_FILE, SliceOrder, per_stack
from service.consistency.stack_evidence import StackEvidence
from service.consistency.stage import (
    StackPoses,
    checked_branch,
    consistent_poses,
    mark_mirrored,
    pool_request,
    request_reference,
    undecided,
)
from service.core.cancellation import checkpoint
from service.core.errors import InvalidParameter
from service.geometry.twin import DEFAULT_PLANE_X_MM
from service.inference import acceptance
from service.inference.estimator import PoseEstimate, PoseEstimator
from service.inference.model_file import ModelInfo
from service.pipeline.image_stage import refine_where_stacks_cross, smooth_images_ahead
from service.pipeline.prepare import PreparedStack, StackUpload
from service.pipeline.unseen_errors import add_unseen_errors
from service.preprocess.one_fetus import apart_from_fetus, brain_centre_mm

STAGE_WORKERS = 3
"""Stacks through the stack-consistency stage at a time (threads: its eigendecompositions release the
GIL). Three, on two cores: a request of three stacks (the usual) has none left to wait for the
others (docs/reports/benchmark-history.md)."""


def stack_poses(est: PoseEstimate, prepared: PreparedStack, net_from_vox: np.ndarray,
                stack_consistency: bool, plane_x_mm: float, expected_error_mm: np.ndarray,
                order: SliceOrder | None = None, error_shape: tuple[float, ...] | None = None,
                depth_gain: float = 0.0, reference: np.ndarray | None = None,
                request_margin: float | None = None, evidence: StackEvidence | None = None,
                keep_evidence: bool = False) -> StackPoses:
    """One stack's poses through the stack-consistency stage (or as the network gave them), from its
    slices' statistics ``est``;
    ``expected_error_mm`` is each slice's expected error: its MC spread times the model's ``mc_error_scale``;
    ``order`` what is known of the stack's acquisition order (default: nothing; the stage chooses);
    ``error_shape`` and ``depth_gain`` the model's ``mc_error_shape`` and ``mc_error_depth_gain``;
    ``reference`` where the request's stacks that decided their branch put the scanner frame, deciding
    this stack's branch where its own margin is under ``request_margin``; ``evidence`` the stack's
    first fit's, where it is fitted again, which that fit kept where ``keep_evidence`` asked
    (:attr:`~service.consistency.stack_fit.StackFit.evidence`)."""
    p = prepared.prepared
    usable = (p.mask_fraction >= acceptance.MIN_MASK_FRACTION) & ~est.degenerate
    return consistent_poses(est.mean, est.twin_mass, net_from_vox, prepared.upload.volume.affine, usable,
                            plane_x_mm, expected_error_mm, stack_consistency, (order or SliceOrder()).times(len(p.inputs)),
                            None if error_shape is None else np.asarray(error_shape), depth_gain, reference,
                            request_margin, evidence, keep_evidence)


@dataclass
class StackPrediction:
    """One stack's answer, as plain data (:mod:`service.pipeline.documents` writes it as the contract's JSON).

    Attributes:
        prepared: the stack as it was prepared (its upload, slices, network inputs, localisation).
        network_from_voxel: ``[n, 4, 4]`` voxel of slice ``k`` -> its network frame.
        estimate: the network's MC statistics of the stack's slices.
        poses: the returned poses and what the stages did (:class:`~service.consistency.stage.StackPoses`).
        reasons: why each slice is not accepted (None: accepted).
        noise_error_mm: what the stack's input noise added to each slice's expected error, in
            quadrature (:func:`~service.preprocess.noise.noise_error_mm`; 0: nothing).
        request_network_error_mm: the request's network error, which its frame error grows
            with (:func:`~service.consistency.frame_error.request_network_error_mm`; NaN: no
            stack had a fit).
        frame_error_mm: what that added to each slice's expected error, in quadrature
            (:func:`~service.consistency.frame_error.frame_error_mm`; 0: nothing).
        own_reasons: each slice's accept flag by its expected error without the request's frame error
            (None: that added nothing): what the slice itself allows. Acquiring a slice again, or
            leaving it out of a reconstruction, does not move the request's frame, so a stream's
            slices worth acquiring again are judged by these.
    """

    prepared: PreparedStack
    network_from_voxel: np.ndarray
    estimate: PoseEstimate
    poses: StackPoses
    reasons: list[str | None]
    noise_error_mm: float = 0.0
    request_network_error_mm: float = float("nan")
    frame_error_mm: float = 0.0
    own_reasons: list[str | None] | None = None


def judge(prepared: PreparedStack, estimate: PoseEstimate, out: StackPoses, threshold: float,
          max_expected_error_mm: float | None, expected: NDArray | None = None) -> list[str | None]:
    """Each returned pose's accept flag (:func:`~service.inference.acceptance.reasons`), by its
    expected error (``expected``: others instead of ``out``'s)."""
    expected = out.expected_error_mm if expected is None else expected
    return acceptance.reasons(prepared.prepared.mask_fraction, estimate.degenerate, out.poses[:, :3, 3],
                              estimate.variance, threshold, out.inconsistent,
                              None if expected is None else np.where(np.isfinite(expected), expected, np.nan),
                              max_expected_error_mm)


def stack_orders(orders: list[SliceOrder] | None, uploads: list[StackUpload]) -> list[SliceOrder]:
    """One acquisition order per stack (:func:`~service.consistency.slice_order.per_stack`), each
    fitting its stack's slice count (:class:`InvalidParameter` naming the field and the file
    otherwise). Where the request says nothing, the order the file holds (a DICOM series' acquisition
    times, along the slice axis), else the stage chooses."""
    try:
        every = per_stack(orders, len(uploads))
    except ValueError as e:
        raise InvalidParameter(f"slice_order: {e}") from None
    out = []
    for i, (order, up) in enumerate(zip(every, uploads)):
        vol = up.volume
        axis = up.slice_axis
        if not order.known and vol.acquisition_order is not None and axis == 2 \
                and len(vol.acquisition_order) == vol.array.shape[2]:
            order = SliceOrder((), vol.acquisition_order, FROM_FILE)
        try:
            order.times(vol.array.shape[axis])
        except ValueError as e:
            raise InvalidParameter(f"slice_order, stack {i} ({up.filename}): {e}") from None   # one value may serve all
        out.append(order)
    return out


def apart_distances(prepared: list[PreparedStack]) -> NDArray[np.float64]:
    """How far each stack's brain lies from the request's fetus where it is not that fetus's, else NaN:
    each mask's brain centre in the scanner frame (the stacks share it) against the request's fetus
    (:func:`~service.preprocess.one_fetus.apart_from_fetus`, the uploaded masks' fetus the request's;
    an uploaded mask of a twin, a file of another scan). Where the stacks divide evenly between two
    fetuses, the first stack of ``prepared`` (the request's first, a stream's first) holds the request's."""
    centres = [brain_centre_mm(p.localisation.mask, p.upload.volume.affine) for p in prepared]
    return apart_from_fetus(centres, [p.localisation.confidence for p in prepared],
                            [p.localisation.method == "mask" for p in prepared])


def set_apart(outs: list[StackPoses], distances: list[float] | NDArray[np.float64]) -> None:
    """Mark the stacks whose brain is not the request's fetus's (:func:`apart_distances`), in place:
    such a stack's ``apart_mm`` says how far; every slice of it is inconsistent (none is accepted: its
    poses place another brain), and the request's later steps leave it out."""
    for out, distance in zip(outs, distances):
        if np.isfinite(distance):
            out.apart_mm = float(distance)
            out.inconsistent = np.ones(len(out.poses), bool)


def weakest_first(outs: list[StackPoses]) -> list[int]:
    """The order the stacks' weak branch decisions are checked against the others in: the weakest
    first (smallest branch margin; a stack without a fit last), so that of two weak stacks that
    disagree the weaker takes the stronger one's branch whatever their order in the request (in
    upload order the first was overruled by the second, and the second had no reference left).

    Example:
        >>> from types import SimpleNamespace as N
        >>> weakest_first([N(fit=N(branch_margin=2.5)), N(fit=None), N(fit=N(branch_margin=1.7))])
        [2, 0, 1]
    """
    def margin(i: int) -> float:
        fit = outs[i].fit
        value = np.inf if fit is None else float(fit.branch_margin)
        return value if np.isfinite(value) else np.inf
    return sorted(range(len(outs)), key=lambda i: (margin(i), i))


def predict(prepared: list[PreparedStack], estimator: PoseEstimator, mc_samples: int,
            threshold: float, stack_consistency: bool = True,
            orders: list[SliceOrder] | None = None,
            image_consistency: bool = True,
            max_expected_error_mm: float | None = None) -> tuple[list[StackPrediction], dict[str, float]]:
    """Run all slices of all stacks through ``estimator`` at once (:func:`estimate_stacks`), then on
    to the poses (:func:`predict_from_estimates`); returns each stack's :class:`StackPrediction` and
    the timings."""
    parts, timings = estimate_stacks(prepared, estimator, mc_samples)
    checkpoint()
    predictions, more = predict_from_estimates(prepared, parts, estimator.info, threshold, stack_consistency, orders,
                                               image_consistency, max_expected_error_mm)
    return predictions, {**timings, **more}


def estimate_stacks(prepared: list[PreparedStack], estimator: PoseEstimator,
                    mc_samples: int) -> tuple[list[PoseEstimate], dict[str, float]]:
    """The network's MC statistics of every stack's slices, all slices in one batched call; and the
    time inference and statistics took."""
    inputs = np.concatenate([s.prepared.inputs for s in prepared])
    t = time.perf_counter()
    est = estimator.estimate(inputs, mc_samples)
    elapsed = time.perf_counter() - t
    timings = dict(getattr(est, "timings", None) or {"inference": elapsed, "statistics": 0.0})
    bounds = np.cumsum([0] + [len(s.prepared.inputs) for s in prepared])
    return [est.part(slice(int(a), int(b))) for a, b in pairwise(bounds)], timings


def predict_from_estimates(prepared: list[PreparedStack], parts: list[PoseEstimate], info: ModelInfo,
                           threshold: float, stack_consistency: bool = True,
                           orders: list[SliceOrder] | None = None, image_consistency: bool = True,
                           max_expected_error_mm: float | None = None,
                           ) -> tuple[list[StackPrediction], dict[str, float]]:
    """Each stack (with its slices' statistics ``parts``) through the stack-consistency stage, the
    stacks' positions pooled where they agree (:func:`~service.consistency.stage.pool_request`) and
    their slices refined where they cross (:func:`refine_where_stacks_cross`; with
    ``image_consistency`` and the stage on; a slice whose brain lost its signal,
    :attr:`~service.pipeline.prepare.PreparedStack.signal_lost`, has no image to compare: it moves
    with its refined neighbours, as a slice the images do not check); returns each stack's
    :class:`StackPrediction` and the timings. ``orders``: what the request says of the stacks' acquisition orders
    (:func:`stack_orders`). ``threshold`` and ``max_expected_error_mm`` (default: the model's)
    decide the accept flags.

    The stages run over the stacks in :func:`canonical_order`, whatever order the request lists them
    in (sums over stacks and the order in which weak stacks are checked round differently), so one
    scan's stacks in any order get the same answer to the bit; the results come back in the
    request's order."""
    orders = stack_orders(orders, [p.upload for p in prepared])
    apart = apart_distances(prepared) if stack_consistency else np.full(len(prepared), np.nan)
    at = canonical_order(prepared)
    results, timings = _predict_in_order([prepared[i] for i in at], [parts[i] for i in at], info, threshold,
                                         stack_consistency, [orders[i] for i in at], image_consistency,
                                         max_expected_error_mm, apart[at])
    return [results[i] for i in np.argsort(at)], timings


def canonical_order(prepared: list[PreparedStack]) -> list[int]:
    """The stacks' indices ordered by what each holds (a digest of its network inputs and its voxel ->
    scanner map), not by where the request lists it: the same order for the same stacks however they
    are listed.

    Example (two lists of the same two stacks):
        >>> from types import SimpleNamespace as N
        >>> a, b = (N(prepared=N(inputs=np.full((2, 4, 4), v, np.float32)), upload=N(volume=N(affine=np.eye(4))))
        ...         for v in (1.0, 2.0))
        >>> [[a, b][i] for i in canonical_order([a, b])] == [[b, a][i] for i in canonical_order([b, a])]
        True
    """
    def digest(s: PreparedStack) -> bytes:
        h = hashlib.sha256(np.ascontiguousarray(s.prepared.inputs))          # the arrays' buffers, not copies
        h.update(np.ascontiguousarray(s.upload.volume.affine, np.float64))
        return h.digest()

    keys = [digest(s) for s in prepared]
    return sorted(range(len(prepared)), key=lambda i: keys[i])


def _predict_in_order(prepared: list[PreparedStack], parts: list[PoseEstimate], info: ModelInfo, threshold: float,
                      stack_consistency: bool, orders: list[SliceOrder], image_consistency: bool,
                      max_expected_error_mm: float | None, apart: NDArray[np.float64],
                      ) -> tuple[list[StackPrediction], dict[str, float]]:
    """:func:`predict_from_estimates` over the stacks in the order given (``orders``: each stack's;
    ``apart``: each stack's :func:`apart_distances`, decided in the request's order)."""
    if max_expected_error_mm is None:
        max_expected_error_mm = getattr(info, "max_expected_error_mm", None)
    timings: dict[str, float] = {}
    plane_x_mm = getattr(info, "symmetry_plane_x_mm", DEFAULT_PLANE_X_MM)
    scale = getattr(info, "mc_error_scale", 1.0)
    t = time.perf_counter()
    frames = [s.network_from_voxel() for s in prepared]
    shape = getattr(info, "mc_error_shape", None)
    gain = float(getattr(info, "mc_error_depth_gain", 0.0))
    refining = stack_consistency and image_consistency and len(prepared) > 1
    smoothed = None
    if refining:                                # on a thread of its own, beside the stack stage
        ahead = ThreadPoolExecutor(max_workers=1)
        smoothed = ahead.submit(smooth_images_ahead, prepared)
        ahead.shutdown(wait=False)
    with ThreadPoolExecutor(max_workers=max(1, min(STAGE_WORKERS, len(prepared)))) as pool:   # LAPACK frees the GIL
        outs = list(pool.map(lambda e, s, nfv, order: stack_poses(e, s, nfv, stack_consistency, plane_x_mm,
                                                                  e.spread_mm * scale, order, shape, gain,
                                                                  keep_evidence=True),
                             parts, prepared, frames, orders))
        set_apart(outs, apart)             # a stack of another fetus: out of the request's steps
        evidence = [None if o.fit is None else o.fit.evidence for o in outs]   # each stack's fit before the others'
        for out in outs:                   # held here alone, for the refits below
            if out.fit is not None:
                out.fit.evidence = None
        def check(i: int) -> StackPoses:       # a weak decision checked against the others
            return checked_branch(outs[i], request_reference(outs[:i] + outs[i + 1:]), lambda ref, margin: stack_poses(
                parts[i], prepared[i], frames[i], True, plane_x_mm, parts[i].spread_mm * scale, orders[i], shape, gain,
                ref, margin, evidence[i]))

        for i in weakest_first(outs) if stack_consistency else ():
            outs[i] = check(i)
        if stack_consistency:              # a stack whose file mirrors its voxels: out of the request's decisions ...
            mirrored = mark_mirrored(outs, [s.upload.volume.affine for s in prepared])
            if mirrored:                   # ... and out of the others' checks, which it pulled its way
                outs = [out if i in mirrored else check(i) for i, out in enumerate(outs)]
        reference = request_reference(outs) if stack_consistency else None
        if reference is not None:          # a stack that did not decide its branch takes the others' word
            outs = list(pool.map(lambda e, s, nfv, order, out, ev: stack_poses(
                e, s, nfv, True, plane_x_mm, e.spread_mm * scale, order, shape, gain, reference, evidence=ev)
                if undecided(out) else out, parts, prepared, frames, orders, outs, evidence))
        evidence.clear()
    if stack_consistency:
        pool_request(outs)
    timings["stack_consistency"] = time.perf_counter() - t
    checkpoint()
    t = time.perf_counter()
    if refining:
        refine_where_stacks_cross(prepared, outs, [~e.degenerate & ~s.signal_lost for e, s in zip(parts, prepared)],
                                  smoothed.result())
    timings["image_consistency"] = time.perf_counter() - t
    sigma = request_network_error_mm([o.fit.noise_mm if o.fit is not None and o.fit.decidable and not o.apart
                                      else np.nan for o in outs], [int((~e.degenerate).sum()) for e in parts])
    frame_mm = float(frame_error_mm(sigma, getattr(info, "frame_error", None)))
    results = []
    for s, e, nfv, out in zip(prepared, parts, frames, outs):
        added = add_unseen_errors(out, info, e, s.input_noise, frame_mm=frame_mm)
        own = None if frame_mm <= 0 or out.expected_error_mm is None else judge(
            s, e, out, threshold, max_expected_error_mm, np.sqrt(np.maximum(out.expected_error_mm ** 2 - frame_mm ** 2, 0.0)))
        results.append(StackPrediction(s, nfv, e, out, judge(s, e, out, threshold, max_expected_error_mm), float(added),
                                       sigma, frame_mm, own))
    return results, timings
