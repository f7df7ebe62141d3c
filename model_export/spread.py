"""Calibrate a model's MC spread into an expected pose error (the ``mc_error_scale`` metadata).

The stack-consistency stage weighs each network pose by its expected error. MC dropout measures
the network's uncertainty, not its error: on the validation volumes the shipped compact model's
twin-min E.D. is 1.45x its MC spread (root mean squares). This module measures that ratio on
single validation slices and writes it into the ONNX file's metadata (weights untouched), where
:class:`service.inference.model_file.ModelInfo` reads it.

Example (with the atlas at hand):
    >>> scale = measure_error_scale(Path("service/models/default/model.onnx"))   # doctest: +SKIP
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx

from model_export.atlas import DEFAULT_ATLAS_ROOT, split
from model_export.simulate import SimulationConfig
from model_export.train import validation_set
from service.geometry import twin
from service.inference.estimator import OnnxPoseEstimator
from service.inference.model_file import load_model


def error_scale(error_mm: np.ndarray, spread_mm: np.ndarray) -> float:
    """``sqrt(mean(error^2) / mean(spread^2))``: the factor from MC spread to expected error.

    Example:
        >>> error_scale(np.array([3.0, 4.0]), np.array([1.5, 2.0]))
        2.0
    """
    return float(np.sqrt(np.mean(np.square(error_mm)) / max(np.mean(np.square(spread_mm)), 1e-12)))


def measure_error_scale(model_path: Path, root: Path = DEFAULT_ATLAS_ROOT, per_volume: int = 60,
                        mc_samples: int = 100, seed: int = 12345) -> dict[str, float]:
    """The twin-min E.D. and MC spread of the model on single validation slices, and their ratio."""
    model = load_model(model_path)
    info = model.info
    _, val_names = split(root)
    cfg = SimulationConfig.validation(size=info.input_size, pixel_mm=info.pixel_spacing_mm)
    val = validation_set(val_names, root, per_volume, seed=seed, config=cfg)
    est = OnnxPoseEstimator(model).estimate(val.inputs, mc_samples)
    plane = info.symmetry_plane_x_mm
    err = twin.twin_min_ed(est.mean, val.poses, plane)
    return {"slices": len(err), "twin_min_ed_rms_mm": float(np.sqrt(np.mean(err ** 2))),
            "spread_rms_mm": float(np.sqrt(np.mean(est.spread_mm ** 2))),
            "mc_error_scale": error_scale(err, est.spread_mm)}


def write_metadata(model_path: Path, updates: dict[str, object]) -> None:
    """Set ``updates`` in the ONNX file's metadata (values as strings), the graph untouched."""
    proto = onnx.load(str(model_path))
    props = {p.key: p.value for p in proto.metadata_props}
    props.update({k: str(v) for k, v in updates.items()})
    del proto.metadata_props[:]
    for k, v in props.items():
        proto.metadata_props.add(key=k, value=v)
    onnx.save(proto, str(model_path))
