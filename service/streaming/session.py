"""One real-time session: slices in as the scanner reconstructs them, poses out, stacks firming up.

The stages are those of ``/v1/predict`` (:mod:`service.pipeline.predict`), run at three moments:

1. **A slice arrives** (:meth:`StreamSession.add_slice`): the slice alone through the stages of
   ``/v1/predict``, its brain seen between its received neighbours, its pose on its stack's branch
   once the stack's model decided it (:mod:`~service.streaming.arrival`).
2. **Between slices** (:meth:`StreamSession.firm_up`): the stack-consistency stage on the slices of
   the open stack received so far, their acquisition order the order they arrived in (or the
   client's ``acquisition_index``), with the branch of the stacks already ended; its fit runs in the
   stage process (:mod:`~service.streaming.background`). Slices whose pose moved by more than
   :data:`UPDATE_MM` (or whose accept flag changed) are returned as updates.
3. **The stack ends** (:meth:`StreamSession.end_stack`): the stack, rebuilt from its slices, goes
   through ``/v1/predict``'s whole pipeline (localisation, N4, preprocessing, inference) and, with
   the stacks ended before it and their network statistics, through the same request-level stages
   (:func:`~service.pipeline.predict.predict_from_estimates`): its poses are those ``/v1/predict``
   gives for these stacks. Earlier stacks' slices that moved are returned as updates; the slices
   worth acquiring again and the session's coverage of the brain come with the stack (the answers:
   :mod:`~service.streaming.answers`).

Every pose an answer holds maps the slice **as sent**: ``network_from_voxel`` of each answer takes
voxel ``(i0, i1, 0, 1)`` of the sent slice to the network frame (composed once, in
:func:`sent_network_from_voxel`). A session is used from two threads (poses, and the background
firm-up); its state changes under one lock, its computations run outside it.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from service.consistency.frame_error import frame_error_mm
from service.consistency.slice_order import STREAMED, SliceOrder
from service.consistency.stage import StackPoses, checked_branch, consistent_poses, request_reference
from service.core.errors import InvalidParameter, SessionFull
from service.geometry.pose import translate
from service.geometry.twin import DEFAULT_PLANE_X_MM
from service.inference import acceptance
from service.inference.estimator import PoseEstimate, PoseEstimator
from service.io.volume import air_floor, magnitude
from service.pipeline.predict import StackPrediction, estimate_stacks, judge, predict_from_estimates
from service.pipeline.prepare import PreparedStack, StackUpload, prepare_stack
from service.pipeline.unseen_errors import add_noise_error, add_unseen_errors
from service.preprocess.localise import Localiser
from service.preprocess.noise import stack_noise
from service.streaming import immediate
from service.streaming.answers import (NOT_RECEIVED, SessionSummary, SliceAnswer, StackAnswer, consistency_decisions,
                                       moved_mm, stack_to_acquire_again)
from service.streaming.arrival import ReceivedSlice, neighbours, pose_alone, prepare_alone
from service.streaming.background import run_in_stage_process
from service.streaming.footprint import array_bytes
from service.streaming.coverage import Coverage, CoveredSlice, coverage
from service.streaming.frames import SliceFrame, SlicesDropped, StreamedStack, check_frame
from service.streaming.options import SessionOptions, StreamLimits

UPDATE_MM = 1.0
"""A slice whose pose moves by more than this (E.D., mm) is sent again as an update."""
MIN_FIRM_UP_SLICES = 4
"""The stack stage runs on an open stack once it has this many slices."""
FIRM_UP_GROWTH = 0.25
"""... and again once the slices it has grew by this share since its last run (at least one more):
the stage's cost grows with the stack, so its total stays near linear in the slices."""
SHOWN_MAX_EXPECTED_MM = 10.0
"""A slice not accepted still shows where the brain is when its expected error is at most this: its
brain pixels extend the brain :mod:`~service.streaming.coverage` counts (not what is covered); one
placed further off would draw brain, and a gap, where there is none."""
END_SHARE = 3.0
"""What a stack's end keeps (the stack rebuilt whole, its preparation and its masks), as a share of its
slices' pixels as float32, with room above what real stacks measure. An open stack reserves it
for every slice up to its largest index as its slices come (the end's volume holds a blank slice
for each that has not), so that no end takes a session past its memory limit."""


@dataclass
class _Ended:
    prepared: PreparedStack
    estimate: PoseEstimate
    order: SliceOrder
    missing: tuple[int, ...] = ()           # the slices it ended without: blank in it, :data:`NOT_RECEIVED`


def sent_network_from_voxel(p: StackPrediction, frames: list[SliceFrame | None]) -> NDArray[np.float64]:
    """``[n, 4, 4]``: voxel ``(i0, i1, 0, 1)`` of each sent slice -> its network frame in the stack ``p``
    (built from those slices): through the scanner and the stack's voxel ``(i0, i1, k)``. A slice that
    never came (None) is the stack's blank slice ``k``: its voxel ``(i0, i1, k)``."""
    affine = p.prepared.upload.volume.affine
    sent = np.stack([affine @ translate([0.0, 0.0, k]) if f is None else f.scanner_from_voxel
                     for k, f in enumerate(frames)])
    return p.network_from_voxel @ np.linalg.inv(affine) @ sent


class StreamSession:
    """A session's stacks and slices, and the stages run on them (see the module)."""

    def __init__(self, estimator: PoseEstimator, localiser: Localiser | None, limits: StreamLimits = StreamLimits(),
                 options: SessionOptions = SessionOptions()) -> None:
        self.estimator, self.localiser, self.limits = estimator, localiser, limits
        info = estimator.info
        self.mc_samples = options.mc_samples
        self.threshold = info.variance_threshold if options.variance_threshold is None else options.variance_threshold
        self.max_expected_error_mm = (getattr(info, "max_expected_error_mm", None)
                                      if options.max_expected_error_mm is None else options.max_expected_error_mm)
        self.bias_correction = options.bias_correction
        self.masks_hold_csf = options.masks_hold_csf
        self.stacks: dict[str, StreamedStack] = {}
        self.slices: dict[str, dict[int, ReceivedSlice]] = {}
        self.fits: dict[str, StackPoses] = {}
        self.placement_errors: dict[str, float | None] = {}   # how far off each fit's placement puts a new slice (mm)
        self.firmed: dict[str, int] = {}
        self.ended: dict[str, _Ended] = {}
        self.finals: dict[str, StackPrediction] = {}
        self.reacquire_sent: dict[str, list[tuple[int, str]]] = {}   # each ended stack's list as last sent
        self.decisions_sent: dict[str, dict] = {}    # each ended stack's consistency_decisions as last sent
        self.reopened: dict[str, _Ended] = {}   # a reopened stack's earlier end, still held
        self.compute_ms: dict[str, float] = {"slices": 0.0, "firm_up": 0.0, "end_stack": 0.0}
        self.held_bytes = 0                     # the received slices' pixels as float32, and what is kept of them
        self._lock = threading.Lock()

    # -- 1. a slice arrives ------------------------------------------------------------------------------
    def add_slice(self, frame: SliceFrame) -> SliceAnswer:
        """The slice's pose, right away (:class:`InvalidParameter` naming the field, the session
        unchanged, when the slice cannot be taken)."""
        t0 = time.perf_counter()
        check_frame(frame, self.limits.max_pixels)
        if frame.index >= self.limits.max_stack_slices:       # so a stack holds no more slices than that either
            raise InvalidParameter(f"slice.index: {frame.index} is beyond the {self.limits.max_stack_slices} slices one "
                                   f"stack may hold (indices 0 to {self.limits.max_stack_slices - 1}); end the stack "
                                   "and send the rest as another")
        pixels = np.asarray(frame.pixels, np.float32)          # as a file's values are read, with its stack's floor
        known = self.stacks.get(frame.stack)
        floor = air_floor(pixels) if known is None else known.floor
        frame = replace(frame, pixels=magnitude(pixels, floor))
        with self._lock:
            # A slice its ended stack has not had (one it ended without, or one past its last, which its
            # end overtook) opens it again; one it has is refused.
            gap = frame.stack in self.ended and frame.index not in getattr(self.stacks.get(frame.stack), "frames", {})
            if frame.stack in self.ended and not gap:
                raise InvalidParameter(f"slice.index: stack {frame.stack!r} has ended with a slice {frame.index}; "
                                       "slices it has not had may still come (end it again then), a new "
                                       "acquisition comes as a new stack under a new name")
            if sum(len(s) for s in self.stacks.values()) >= self.limits.max_slices:
                raise SessionFull(f"slice: a session holds at most {self.limits.max_slices} slices; "
                                  "end it and start another")
            if frame.stack not in self.stacks and len(self.stacks) >= self.limits.max_stacks:
                raise InvalidParameter(f"slice.stack: a session holds at most {self.limits.max_stacks} stacks; "
                                       "end it and start another (its stacks may go on)")
            size = np.asarray(frame.pixels).size * 4
            others = sum(v for k, v in self.reserved.items() if k != frame.stack)
            if self.held_bytes + others + size + self._end_reserve(frame.stack, frame) > self.limits.max_bytes:
                raise SessionFull(f"slice: a session keeps at most {self.limits.max_bytes / 2**20:.3g} MB (its "
                                  "slices, their preparation and their stacks' ends); end it and start another")
            stack = self.stacks.get(frame.stack) or StreamedStack(frame.stack, floor=floor)
            stack.add(frame)
            self.stacks[frame.stack] = stack
            self.held_bytes += size
            around = neighbours(stack, frame.index)
            received = {k: st.brain_map for k, st in self.slices.get(frame.stack, {}).items() if st.brain_map is not None}
            step_mm = stack.step_mm()
            fit, placement_mm = self.fits.get(frame.stack), self.placement_errors.get(frame.stack)   # of one firm-up
            noise = [st.prepared.input_noise for st in self.slices.get(frame.stack, {}).values()]
        try:                        # a slice that gets no answer is not kept: it may come again, its stack end
            state = prepare_alone(self.estimator, self.localiser, frame, self.mc_samples, self.masks_hold_csf, around,
                                  received, step_mm)
            alone = pose_alone(self.estimator.info, state, fit, placement_mm,
                               stack_noise([*noise, state.prepared.input_noise]))
            answer = SliceAnswer(frame.stack, frame.index, self._judged(state.prepared, state.network_from_voxel,
                                                                         state.estimate, alone))
            kept = array_bytes(state.prepared, state.estimate, [state.brain_map], besides=(frame.pixels,))
        except Exception:
            with self._lock:
                stack.remove(frame.index)
                self.held_bytes -= size
                if not len(stack):
                    del self.stacks[frame.stack]
            raise
        with self._lock:
            self.slices.setdefault(frame.stack, {})[frame.index] = state
            state.answer = answer
            self.held_bytes += kept
            if gap:
                self._reopen(frame.stack)
        answer.compute_ms = (time.perf_counter() - t0) * 1e3
        self.compute_ms["slices"] += answer.compute_ms
        return answer

    def _judged(self, prepared: PreparedStack, network_from_voxel: NDArray, est: PoseEstimate,
                out: StackPoses) -> StackPrediction:
        return StackPrediction(prepared, network_from_voxel, est, out,
                               judge(prepared, est, out, self.threshold, self.max_expected_error_mm))

    # -- 2. between slices ---------------------------------------------------------------------------------
    def firm_up(self, stack: str) -> list[SliceAnswer]:
        """The open ``stack``'s received slices through the stack-consistency stage (when enough
        arrived since its last run: :data:`FIRM_UP_GROWTH`); the answers of those that moved by
        more than :data:`UPDATE_MM` or changed their accept flag."""
        t0 = time.perf_counter()
        with self._lock:
            have, last = len(self.slices.get(stack, {})), self.firmed.get(stack, 0)
            if stack in self.ended or have < max(MIN_FIRM_UP_SLICES, last + max(1, int(FIRM_UP_GROWTH * last))):
                return []
            self.firmed[stack] = have
            states = [self.slices[stack][k] for k in sorted(self.slices[stack])]
            order = self.stacks[stack].arrival_order()
            reference = request_reference([p.poses for p in self.finals.values()])
        info = self.estimator.info
        est = PoseEstimate(*(np.concatenate([getattr(s.estimate, f) for s in states])
                             for f in ("mean", "variance", "degenerate", "twin_mass", "spread_mm")))
        nfv = np.concatenate([s.network_from_voxel for s in states])
        network_from_scanner = nfv @ np.linalg.inv(np.stack([s.frame.scanner_from_voxel for s in states]))
        rank = {k: r for r, k in enumerate(k for k in order if k in {s.frame.index for s in states})}
        times = {STREAMED: np.array([rank[s.frame.index] for s in states])}
        usable = (np.concatenate([s.prepared.prepared.mask_fraction for s in states]) >= acceptance.MIN_MASK_FRACTION) \
            & ~est.degenerate
        shape = getattr(info, "mc_error_shape", None)
        plane = getattr(info, "symmetry_plane_x_mm", DEFAULT_PLANE_X_MM)
        args = (est.mean, est.twin_mass, network_from_scanner, np.eye(4), usable, plane,
                est.spread_mm * getattr(info, "mc_error_scale", 1.0), True, times,
                None if shape is None else np.asarray(shape), float(getattr(info, "mc_error_depth_gain", 0.0)))
        out = run_in_stage_process(consistent_poses, *args, reference)
        out = checked_branch(out, reference, lambda ref, margin: run_in_stage_process(consistent_poses, *args, ref, margin))
        sigma = out.fit.noise_mm if out.fit is not None and out.fit.decidable else float("nan")
        add_unseen_errors(out, info, est, frame_mm=float(frame_error_mm(sigma, getattr(info, "frame_error", None))))
        placement_mm = None
        if out.fit is not None and out.fit.atlas_from_scanner is not None:
            placement_mm = immediate.placement_error_mm(out.expected_error_mm, out.poses, out.fit.atlas_from_scanner,
                                                        network_from_scanner, times[STREAMED], usable & ~out.inconsistent)
        # The noise error after the placement's, which later answers weigh and then add their own to.
        add_noise_error(out, info, stack_noise([s.prepared.input_noise for s in states]))
        answers = [SliceAnswer(stack, s.frame.index, self._judged(s.prepared, s.network_from_voxel, s.estimate,
                                                                  out.part(slice(i, i + 1)))) for i, s in enumerate(states)]
        with self._lock:
            if stack in self.ended:
                return []
            self.fits[stack] = out
            self.placement_errors[stack] = placement_mm
            changed = self._changed(stack, answers)
        self.compute_ms["firm_up"] += (time.perf_counter() - t0) * 1e3
        return changed

    def _changed(self, stack: str, answers: list[SliceAnswer]) -> list[SliceAnswer]:
        """Of ``answers`` (new poses of ``stack``'s slices), those that moved or changed their accept
        flag or its reason since last sent; they become the last sent (call under the lock)."""
        out = []
        for a in answers:
            state = self.slices[stack][a.index]
            last = state.answer
            reason = lambda x: x.prediction.reasons[x.row]  # noqa: E731
            if last is None or reason(last) != reason(a) or moved_mm(last, a, state.network_from_voxel[0]) > UPDATE_MM:
                out.append(a)
                state.answer = a
        return out

    def _forget(self, stack: str, index: int) -> None:
        """Drop slice ``index`` of ``stack`` and what the session kept of it (under the lock)."""
        frame = self.stacks[stack].frames[index]
        self.stacks[stack].remove(index)
        self.held_bytes -= np.asarray(frame.pixels).size * 4
        state = self.slices.get(stack, {}).pop(index, None)
        if state is not None:
            self.held_bytes -= array_bytes(state.prepared, state.estimate, [state.brain_map], besides=(frame.pixels,))

    def _end_reserve(self, stack: str, new: SliceFrame | None = None) -> float:
        """What ``stack`` reserves for its end (with the slice ``new`` too): :data:`END_SHARE` of a
        slice's pixel bytes for each slice up to its largest index; nothing where it has ended; where
        it was reopened by a slice it had not had, for the slices past those its earlier end, still
        held, spanned (ending again keeps as much for those)."""
        if stack in self.ended:
            return 0.0
        frames = self.stacks[stack].frames if stack in self.stacks else {}
        largest = max(max(frames, default=-1), -1 if new is None else new.index)
        if largest < 0:
            return 0.0
        size = np.asarray((new or next(iter(frames.values()))).pixels).size * 4
        earlier = self.reopened.get(stack)
        spanned = 0 if earlier is None else earlier.prepared.upload.volume.array.shape[2]
        return END_SHARE * size * max(0, largest + 1 - spanned)

    @property
    def reserved(self) -> dict[str, float]:
        """Each open stack's reserve for its end (:meth:`_end_reserve`), worked out from its slices
        whenever asked: no count to keep in step as slices come, fail, are dropped or end."""
        return {name: r for name in self.stacks if (r := self._end_reserve(name))}

    def _reopen(self, stack: str) -> None:
        """A slice the ended ``stack`` has not had has come: the stack is open again, its final poses
        withdrawn until it ends again (under the lock). What its end prepared stays counted until
        then: its slices' last answers hold it."""
        self.reopened[stack] = self.ended.pop(stack)
        self.finals.pop(stack, None)

    # -- 3. the stack ends ------------------------------------------------------------------------------------
    def end_stack(self, stack: str) -> StackAnswer:
        """The stack's final poses, as ``/v1/predict`` gives them with the stacks ended before it.
        Slices below its largest index that have not come are judged blank, their reason
        :data:`NOT_RECEIVED`, and listed to acquire again; they may still come, as may slices past its
        last that its end overtook, and reopen the stack (:meth:`add_slice`)."""
        t0 = time.perf_counter()
        with self._lock:
            if stack in self.ended:
                raise InvalidParameter(f"end_stack.stack: stack {stack!r} has already ended")
            if stack not in self.stacks:
                raise InvalidParameter(f"end_stack.stack: no slice of a stack {stack!r} has arrived")
            streamed = self.stacks[stack]
            off = streamed.off_line()
            if off:                 # a slice taken while the step was known from few slices: let it come again
                for k in off:
                    self._forget(stack, k)
                raise SlicesDropped(f"end_stack.stack: the slices {off[:10]} of stack {stack!r} lie off the even "
                                    "spacing of its other slices along their normal; they are dropped from the "
                                    "stack: send them again where they belong, then end_stack again", off)
            volume, mask = streamed.volume(checked=True)
            missing = tuple(streamed.missing())
            order = SliceOrder((), streamed.arrival_order() + missing, STREAMED)
            before = dict(self.ended)
        info = self.estimator.info
        upload = StackUpload(stack, volume, mask, None if mask is None else f"{stack} (mask frames)",
                             mask_holds_csf=self.masks_hold_csf, mask_may_be_region=False)
        prepared = prepare_stack(upload, info, self.bias_correction, self.localiser)
        prepared.cut_by_field_of_view                  # worked out here, not under the session's lock at its answer
        (estimate,), timings = estimate_stacks([prepared], self.estimator, self.mc_samples)
        ended = {**before, stack: _Ended(prepared, estimate, order, missing)}
        names = list(ended)
        predictions, more = predict_from_estimates([ended[n].prepared for n in names], [ended[n].estimate for n in names],
                                                   info, self.threshold, True, [ended[n].order for n in names], True,
                                                   self.max_expected_error_mm)
        timings.update(more)
        with self._lock:
            self.ended[stack] = ended[stack]
            earlier = self.reopened.pop(stack, None)                # the stack as prepared whole, for its earlier end
            self.held_bytes += array_bytes(ended[stack]) - (0 if earlier is None else array_bytes(earlier))
            for state in self.slices.get(stack, {}).values():     # its slices' maps serve no later slice
                self.held_bytes -= array_bytes([state.brain_map])
                state.brain_map = None
            updates = []
            for name, p in zip(names, predictions):
                sent, gone = self.stacks[name].frames, ended[name].missing
                received = lambda flags: None if flags is None else [NOT_RECEIVED if k in gone else r  # noqa: E731
                                                                     for k, r in enumerate(flags)]
                p = replace(p, network_from_voxel=sent_network_from_voxel(p, [sent.get(k) for k in range(len(p.reasons))]),
                            reasons=received(p.reasons), own_reasons=received(p.own_reasons))
                answers = [SliceAnswer(name, k, p, k) for k in range(len(p.reasons)) if k in sent]
                self.finals[name] = p
                if name == stack:
                    for a in answers:
                        self.slices[stack][a.index].answer = a
                    final = p
                else:
                    updates += self._changed(name, answers)
            covered, shown = self._covered()
            alone = len(names) == 1
            lists = {n: stack_to_acquire_again(self.finals[n], alone) for n in names}
            changed = {n: r for n, r in lists.items() if n != stack and r != self.reacquire_sent.get(n)}
            self.reacquire_sent.update(lists)
            decided = {n: consistency_decisions(self.finals[n]) for n in names}
            restated = {n: self.finals[n] for n in names
                        if n != stack and decided[n] != self.decisions_sent.get(n)}
            self.decisions_sent.update(decided)
        answer = StackAnswer(stack, final, updates, lists[stack], coverage(covered, shown), timings, alone, changed,
                             restated)
        self.compute_ms["end_stack"] += (time.perf_counter() - t0) * 1e3
        return answer

    def _covered(self) -> tuple[list[CoveredSlice], list[CoveredSlice]]:
        """The accepted slices of the session, and those with the slices with brain whose pose is
        roughly right (expected within :data:`SHOWN_MAX_EXPECTED_MM`, not outside the atlas or
        degenerate), at their latest poses with their brain masks: what :func:`coverage` takes (under
        the lock)."""
        covered, shown = [], []
        for states in self.slices.values():
            for s in states.values():
                a = s.answer
                if a is None or not (a.prediction.reasons[a.row] is None or self._placed(a)):
                    continue
                brain = np.asarray(a.prediction.prepared.localisation.mask[:, :, a.row], bool)
                found = CoveredSlice(a.prediction.poses.poses[a.row] @ a.prediction.network_from_voxel[a.row], brain)
                shown.append(found)
                if a.prediction.reasons[a.row] is None:
                    covered.append(found)
        return covered, shown

    @staticmethod
    def _placed(answer: SliceAnswer) -> bool:
        """A slice not accepted whose pose still says where the brain it shows lies (see :meth:`_covered`)."""
        p, row = answer.prediction, answer.row
        expected = p.poses.expected_error_mm
        return (p.reasons[row] in (acceptance.INCONSISTENT, acceptance.HIGH_EXPECTED_ERROR, acceptance.HIGH_VARIANCE)
                and expected is not None and bool(expected[row] <= SHOWN_MAX_EXPECTED_MM))

    def coverage(self) -> Coverage:
        with self._lock:
            covered, shown = self._covered()
        return coverage(covered, shown)

    def summary(self) -> SessionSummary:
        with self._lock:
            names = list(self.stacks)
            n = sum(len(s) for s in self.stacks.values())
            final = {k: stack_to_acquire_again(p, False) for k, p in self.finals.items()}   # nothing more comes
            unfinished = {k: s.missing() for k, s in self.stacks.items() if k not in self.finals}
        return SessionSummary(names, self.coverage(), n, dict(self.compute_ms), final, unfinished)
