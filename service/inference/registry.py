"""The models a server offers: every ``<models_dir>/<name>/model.onnx``, loaded once at start-up."""

from __future__ import annotations

import logging
from pathlib import Path

from service.core.errors import NotFound
from service.core.onnx import load_models
from service.inference.estimator import OnnxPoseEstimator, PoseEstimator
from service.inference.model_file import load_model

log = logging.getLogger(__name__)


class ModelRegistry:
    """Name -> :class:`PoseEstimator`; ``default_name`` is what ``model=default`` means."""

    def __init__(self, estimators: dict[str, PoseEstimator], default_name: str = "default",
                 models_dir: Path | None = None) -> None:
        self.estimators = estimators
        self.default_name = default_name
        self.models_dir = models_dir
        """The folder the estimators were loaded from (:meth:`from_directory`; None: stand-ins, no files):
        where each model's card is, and whose files a job's worker loads again (:meth:`served_sha256`)."""

    @classmethod
    def from_directory(cls, models_dir: Path, default_name: str = "default", threads: int = 0) -> "ModelRegistry":
        """Every model of ``models_dir`` (:func:`~service.core.onnx.load_models`:
        :class:`~service.core.errors.UnusableModelFile` names a file that does not load)."""
        estimators: dict[str, PoseEstimator] = load_models(
            models_dir, "SVRNET_MODELS_DIR", lambda path: OnnxPoseEstimator(load_model(path, threads)))
        for name in estimators:
            log.info("model loaded", extra={"model": name})
        return cls(estimators, default_name, Path(models_dir))

    def resolve(self, name: str) -> str:
        """The loaded model's name that ``name`` means: ``"default"`` is ``default_name``
        (``SVRNET_DEFAULT_MODEL``); raises :class:`NotFound` (404) naming the field otherwise.

        Example:
            >>> ModelRegistry({"v2": None}, default_name="v2").resolve("default")
            'v2'
        """
        resolved = self.default_name if name == "default" else name
        if resolved not in self.estimators:
            known = ", ".join(sorted(self.estimators)) or "none loaded"
            raise NotFound(f"model: unknown model {name!r} (available: {known})")
        return resolved

    def get(self, name: str) -> PoseEstimator:
        """The estimator ``name`` resolves to (see :meth:`resolve`)."""
        return self.estimators[self.resolve(name)]

    def served_sha256(self, name: str) -> str | None:
        """The sha256 of the model file served as ``name`` (what a job records at its submission, to know
        its worker loads the same file); None where the estimators are no files (a stand-in)."""
        return self.get(name).info.sha256 if self.models_dir is not None else None

    def describe(self) -> list[dict]:
        """The ``GET /v1/models`` body."""
        out = []
        for name, est in sorted(self.estimators.items()):
            i = est.info
            out.append({**i.reference(name), "input_size": i.input_size, "spacing_mm": i.pixel_spacing_mm,
                        "label_type": i.label_type, "variance_threshold": i.variance_threshold,
                        "max_expected_error_mm": i.max_expected_error_mm, "trained_on": i.trained_on,
                        "mc_seed": i.mc_seed, "licences": i.licences,
                        "card": self.models_dir is not None and (self.models_dir / name / "card.md").is_file()})
        return out
