"""The pose estimator: network inputs -> MC-dropout pose samples -> Fréchet mean and variance.

:class:`PoseEstimator` is the seam the API depends on (tests swap in an oracle). The ONNX
implementation runs all slices of a request in a few batched calls, each running the trunk once
per slice and view and the dropout head ``mc_samples`` times in all (:mod:`service.inference.views`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from service.core.threads import side_by_side, two_threads
from service.geometry import anchors, encodings, se3, twin
from service.inference.model_file import LoadedModel, ModelInfo
from service.inference.views import sample_views


MIN_SLICES_PER_THREAD = 8
"""Fewer slices than twice this are reduced in one thread (a streamed slice, a short stack)."""
MAX_SAMPLES_AT_ONCE = 65536
"""Slices x MC samples whose labels :meth:`OnnxPoseEstimator.estimate` holds at once: a request's
slices go through the network and are reduced in chunks of this many samples, so that memory is
bounded by the chunk, not by the request's slices x ``mc_samples`` (docs/deployment.md, "Memory").
A slice's statistics do not depend on the chunk it is in (every row of a call has the same dropout
draws)."""


PER_SLICE = ("mean", "variance", "degenerate", "twin_mass", "spread_mm")
""":class:`PoseEstimate`'s per-slice fields, in order."""


@dataclass
class PoseEstimate:
    """Per-slice statistics of the MC samples.

    Attributes:
        mean: ``[B, 4, 4]`` Fréchet mean pose of the network frame in atlas space.
        variance: ``[B]`` geodesic variance (the paper's confidence measure).
        degenerate: ``[B]`` predictions whose anchor points collapse (anchor models only).
        twin_mass: ``[B]`` fraction of the MC samples that sat on the other twin of ``mean``
            (<= 0.5: ``mean`` is on the majority branch; see :func:`service.geometry.twin.align_samples`).
        spread_mm: ``[B]`` root-mean-square E.D. (anchor points, mm) of the aligned samples about
            ``mean``: the network's own uncertainty in the units of the pose error.
    """

    mean: NDArray[np.float64]
    variance: NDArray[np.float64]
    degenerate: NDArray[np.bool_]
    twin_mass: NDArray[np.float64] | None = None
    spread_mm: NDArray[np.float64] | None = None
    timings: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.twin_mass is None:
            self.twin_mass = np.zeros(len(self.mean))
        if self.spread_mm is None:
            self.spread_mm = np.zeros(len(self.mean))

    @property
    def estimated(self) -> NDArray[np.bool_]:
        """``[B]`` the slices the network saw (:meth:`scattered` gives the others a NaN spread)."""
        return np.isfinite(self.spread_mm)

    def part(self, which: slice) -> "PoseEstimate":
        """The statistics of the slices ``which`` (one stack of a request)."""
        return PoseEstimate(*(getattr(self, name)[which] for name in PER_SLICE))

    @classmethod
    def scattered(cls, seen_estimate: "PoseEstimate", seen: NDArray[np.bool_]) -> "PoseEstimate":
        """The statistics of all ``len(seen)`` slices when only those ``seen`` went through the network
        (``seen_estimate``, in their order): a slice not seen (no brain in it) has no pose of its own
        (the identity), a NaN variance and spread (:attr:`estimated` is False), and is not
        degenerate.

        Example:
            >>> one = PoseEstimate(np.eye(4)[None] * 2, np.array([3.0]), np.array([True]))
            >>> both = PoseEstimate.scattered(one, np.array([False, True]))
            >>> both.variance.tolist(), both.degenerate.tolist(), float(both.mean[0, 0, 0])
            ([nan, 3.0], [False, True], 1.0)
        """
        seen = np.asarray(seen, bool)
        n = len(seen)
        out = cls(np.broadcast_to(np.eye(4), (n, 4, 4)).copy(), np.full(n, np.nan), np.zeros(n, bool),
                  np.zeros(n), np.full(n, np.nan))
        for name in PER_SLICE:
            getattr(out, name)[seen] = getattr(seen_estimate, name)
        return out

    @classmethod
    def joined(cls, parts: list["PoseEstimate"]) -> "PoseEstimate":
        """The statistics of ``parts``' slices, one part after the other (:meth:`part` undone)."""
        return cls(*(np.concatenate([getattr(p, name) for p in parts]) for name in PER_SLICE))


def shown(inputs: NDArray) -> NDArray[np.bool_]:
    """``[B]`` which network inputs ``[B, L, L]`` hold anything: an all-zero input (a slice with no
    brain; everything outside the mask is 0) shows the network nothing, and is not run.

    Example:
        >>> shown(np.stack([np.zeros((2, 2)), np.eye(2)])).tolist()
        [False, True]
    """
    x = np.asarray(inputs)
    return x.reshape(len(x), -1).any(axis=1)


class PoseEstimator(Protocol):
    """Anything that turns preprocessed slices ``[B, L, L]`` into pose estimates."""

    info: ModelInfo

    def estimate(self, inputs: NDArray[np.float32], mc_samples: int) -> PoseEstimate: ...


def statistics(labels: NDArray, label_type: str, plane_x_mm: float = twin.DEFAULT_PLANE_X_MM) -> PoseEstimate:
    """Decode MC labels ``[B, N, D]`` and reduce them to :class:`PoseEstimate`, twin-aware
    (:func:`slice_statistics`), the two halves of the slices side by side in two threads."""
    half = len(labels) // 2
    if half < MIN_SLICES_PER_THREAD:
        return slice_statistics(labels, label_type, plane_x_mm)
    return PoseEstimate.joined(two_threads(lambda h: slice_statistics(labels[:half] if h == 0 else labels[half:],
                                                                      label_type, plane_x_mm)))


def slice_statistics(labels: NDArray, label_type: str, plane_x_mm: float = twin.DEFAULT_PLANE_X_MM) -> PoseEstimate:
    """Decode MC labels ``[B, N, D]`` and reduce them to :class:`PoseEstimate`, twin-aware.

    The samples of each slice are put on one branch first (a sample and its left-right twin
    render the same image), so a split between the twins is not taken for spread, nor lost: it is
    reported as ``twin_mass``. From a single sample the variance is NaN (not measured), so that no
    slice is accepted on a spread that was never seen. A slice with a non-finite sample is
    ``degenerate`` (it neither votes in its stack's model nor is accepted) and its statistics are
    those of its finite samples alone (none: no spread, no variance).

    Example (one NaN among a slice's three samples; a slice of one finite sample of three):
        >>> lab = np.tile(encodings.encode("anchor", np.eye(4)[None]), (2, 3, 1))
        >>> lab[0, 1, 0] = lab[1, :2, 0] = np.nan
        >>> est = slice_statistics(lab, "anchor")
        >>> est.degenerate.tolist(), bool(np.isfinite(est.mean).all()), np.isnan(est.variance).tolist()
        ([True, True], True, [False, True])
    """
    lab = np.asarray(labels, dtype=np.float64)
    finite = np.isfinite(lab).all(axis=-1)                           # [B, N]
    if finite.all():
        return _reduced(lab, label_type, plane_x_mm)
    est = _reduced(np.where(finite[..., None], lab, 0.0), label_type, plane_x_mm)
    for b in np.flatnonzero(~finite.all(axis=1)):     # a broken sample: the slice's finite samples alone
        kept = lab[b][finite[b]]
        if len(kept):
            own = _reduced(kept[None], label_type, plane_x_mm)
            est.mean[b], est.variance[b], est.twin_mass[b], est.spread_mm[b] = (
                own.mean[0], own.variance[0], own.twin_mass[0], own.spread_mm[0])
        else:
            est.variance[b] = est.twin_mass[b] = est.spread_mm[b] = np.nan
        est.degenerate[b] = True
    return est


def _reduced(lab: NDArray[np.float64], label_type: str, plane_x_mm: float) -> PoseEstimate:
    """:func:`slice_statistics` of finite labels ``[B, N, D]``."""
    poses = encodings.decode(label_type, lab)                        # [B, N, 4, 4]
    aligned, flipped = twin.align_samples(poses, plane_x_mm)
    mean, var = se3.frechet_mean_and_variance(aligned)
    if lab.shape[1] < 2:            # one pass measures no spread: its variance is unknown, not 0
        var = np.full(len(lab), np.nan)
    if label_type == "anchor":
        degenerate = anchors.degenerate(lab).mean(axis=1) > 0.5
    else:
        degenerate = np.zeros(len(lab), dtype=bool)
    pts = anchors.encode(aligned).reshape(aligned.shape[:-2] + (3, 3))
    centre = anchors.encode(mean).reshape(mean.shape[:-2] + (1, 3, 3))
    spread = np.sqrt(np.mean(np.linalg.norm(pts - centre, axis=-1).mean(axis=-1) ** 2, axis=-1))
    return PoseEstimate(mean, np.asarray(var, np.float64), degenerate, flipped.mean(axis=-1).astype(np.float64), spread)


class OnnxPoseEstimator:
    """MC-dropout pose estimation with an exported model in onnxruntime."""

    def __init__(self, model: LoadedModel, batch_slices: int = 64) -> None:
        self.model = model
        self.info = model.info
        self.batch_slices = batch_slices

    def sample_labels(self, inputs: NDArray[np.float32], mc_samples: int) -> NDArray:
        """Labels ``[B, N, D]`` of the slices, the ``N = mc_samples`` samples shared among the model's
        test-time views (``info.tta_views``), each view with its own dropout draws;
        ``mc_samples = 0``: one deterministic pass per view."""
        views = lambda x, n: self.run(x, n, group=len(inputs))  # noqa: E731 - the views come as groups of B rows
        return sample_views(views, inputs, mc_samples, self.info.label_type, self.info.symmetry_plane_x_mm,
                            self.info.tta_views)

    def run(self, inputs: NDArray[np.float32], mc_samples: int, group: int | None = None) -> NDArray[np.float32]:
        """Raw labels ``[B, N, D]``; ``mc_samples = 0`` gives one deterministic pass (N = 1). Rows come
        in groups of ``group`` (default: one group), group ``g`` with dropout draws ``g``
        (:meth:`~service.inference.model_file.LoadedModel.draws`), in calls of at most
        :attr:`batch_slices` rows (two at a time where the model's session is set so:
        :attr:`~service.inference.model_file.LoadedModel.side_by_side`)."""
        passes = np.ones(mc_samples, np.float32) if mc_samples > 0 else np.zeros(1, np.float32)
        x = np.asarray(inputs, dtype=np.float32)
        group = max(int(group or len(x)), 1)
        calls = [(x[start:start + group][i:i + self.batch_slices], draw)
                 for draw, start in enumerate(range(0, len(x), group)) for i in range(0, min(group, len(x) - start),
                                                                                   self.batch_slices)]
        run = lambda call: self.model.run(call[0], passes, call[1])  # noqa: E731
        chunks = side_by_side(run, calls) if self.model.side_by_side else [run(call) for call in calls]
        return np.concatenate(chunks) if chunks else np.zeros((0, len(passes), 0), np.float32)

    def estimate(self, inputs: NDArray[np.float32], mc_samples: int) -> PoseEstimate:
        """The MC statistics of every slice of ``inputs [B, L, L]``, in chunks of
        :data:`MAX_SAMPLES_AT_ONCE` samples. An input that is not :func:`shown` to the network gets
        no pose (:meth:`PoseEstimate.scattered`); the others' draws do not depend on it, so their
        statistics are those of a call with it."""
        x = np.asarray(inputs, dtype=np.float32)
        seen = shown(x)
        run = x if seen.all() else x[seen]
        chunk = max(1, MAX_SAMPLES_AT_ONCE // max(int(mc_samples), 1))
        parts, timings = [], {"inference": 0.0, "statistics": 0.0}
        for start in range(0, len(run), chunk):
            t0 = time.perf_counter()
            labels = self.sample_labels(run[start:start + chunk], mc_samples)
            t1 = time.perf_counter()
            parts.append(statistics(labels, self.info.label_type, self.info.symmetry_plane_x_mm))
            del labels                                 # the next chunk's labels take its place
            timings["inference"] += t1 - t0
            timings["statistics"] += time.perf_counter() - t1
        result = PoseEstimate.joined(parts) if parts else PoseEstimate(np.zeros((0, 4, 4)), np.zeros(0),
                                                                        np.zeros(0, bool))
        if not seen.all():
            result = PoseEstimate.scattered(result, seen)
        result.timings = timings
        return result
