"""The models a server offers: every ``<models_dir>/<name>/model.onnx``, loaded once at start-up."""

from __future__ import annotations

import logging
from pathlib import Path

from service.core.errors import NotFound
from service.inference.estimator import OnnxPoseEstimator, PoseEstimator
from service.inference.model_file import load_model

log = logging.getLogger(__name__)


class ModelRegistry:
    """Name -> :class:`PoseEstimator`; ``default_name`` is what ``model=default`` means."""

    def __init__(self, estimators: dict[str, PoseEstimator], default_name: str = "default") -> None:
        self.estimators = estimators
        self.default_name = default_name

    @classmethod
    def from_directory(cls, models_dir: Path, default_name: str = "default", threads: int = 0) -> "ModelRegistry":
        estimators: dict[str, PoseEstimator] = {}
        for path in sorted(Path(models_dir).glob("*/model.onnx")):
            estimators[path.parent.name] = OnnxPoseEstimator(load_model(path, threads))
            log.info("model loaded", extra={"model": path.parent.name})
        return cls(estimators, default_name)

    def get(self, name: str) -> PoseEstimator:
        """The estimator called ``name``; raises :class:`NotFound` (404) naming the field otherwise."""
        try:
            return self.estimators[name]
        except KeyError:
            known = ", ".join(sorted(self.estimators)) or "none loaded"
            raise NotFound(f"model: unknown model {name!r} (available: {known})") from None

    def describe(self) -> list[dict]:
        """The ``GET /v1/models`` body."""
        out = []
        for name, est in sorted(self.estimators.items()):
            i = est.info
            out.append({"name": name, "version": i.version, "backbone": i.backbone, "sha256": i.sha256,
                        "input_size": i.input_size, "spacing_mm": i.pixel_spacing_mm, "label_type": i.label_type,
                        "variance_threshold": i.variance_threshold, "trained_on": i.trained_on})
        return out
