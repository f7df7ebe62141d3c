"""The pose estimator: network inputs -> MC-dropout pose samples -> Fréchet mean and variance.

:class:`PoseEstimator` is the seam the API depends on (tests swap in an oracle). The ONNX
implementation runs all slices of a request in a few batched calls, each running the trunk once
per slice and the dropout head ``mc_samples`` times.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from service.geometry import anchors, encodings, se3
from service.inference.model_file import LoadedModel, ModelInfo


@dataclass
class PoseEstimate:
    """Per-slice statistics of the MC samples.

    Attributes:
        mean: ``[B, 4, 4]`` Fréchet mean pose of the network frame in atlas space.
        variance: ``[B]`` geodesic variance (the paper's confidence measure).
        degenerate: ``[B]`` predictions whose anchor points collapse (anchor models only).
    """

    mean: NDArray[np.float64]
    variance: NDArray[np.float64]
    degenerate: NDArray[np.bool_]
    timings: dict[str, float] = field(default_factory=dict)


class PoseEstimator(Protocol):
    """Anything that turns preprocessed slices ``[B, L, L]`` into pose estimates."""

    info: ModelInfo

    def estimate(self, inputs: NDArray[np.float32], mc_samples: int) -> PoseEstimate: ...


def statistics(labels: NDArray, label_type: str) -> PoseEstimate:
    """Decode MC labels ``[B, N, D]`` and reduce them to :class:`PoseEstimate`."""
    lab = np.asarray(labels, dtype=np.float64)
    poses = encodings.decode(label_type, lab)                        # [B, N, 4, 4]
    mean, var = se3.frechet_mean_and_variance(poses)
    if label_type == "anchor":
        degenerate = anchors.degenerate(lab).mean(axis=1) > 0.5
    else:
        degenerate = np.zeros(len(lab), dtype=bool)
    return PoseEstimate(mean, var, degenerate)


class OnnxPoseEstimator:
    """MC-dropout pose estimation with an exported model in onnxruntime."""

    def __init__(self, model: LoadedModel, batch_slices: int = 64) -> None:
        self.model = model
        self.info = model.info
        self.batch_slices = batch_slices

    def sample_labels(self, inputs: NDArray[np.float32], mc_samples: int) -> NDArray[np.float32]:
        """Raw labels ``[B, N, D]``; ``mc_samples = 0`` gives one deterministic pass (N = 1)."""
        passes = np.ones(mc_samples, np.float32) if mc_samples > 0 else np.zeros(1, np.float32)
        x = np.asarray(inputs, dtype=np.float32)
        chunks = [self.model.run(x[i:i + self.batch_slices], passes) for i in range(0, len(x), self.batch_slices)]
        return np.concatenate(chunks) if chunks else np.zeros((0, len(passes), 0), np.float32)

    def estimate(self, inputs: NDArray[np.float32], mc_samples: int) -> PoseEstimate:
        t0 = time.perf_counter()
        labels = self.sample_labels(inputs, mc_samples)
        t1 = time.perf_counter()
        result = statistics(labels, self.info.label_type)
        result.timings = {"inference": t1 - t0, "statistics": time.perf_counter() - t1}
        return result
