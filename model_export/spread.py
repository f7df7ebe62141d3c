"""Calibrate a model's MC spread into an expected pose error (the ``mc_error_scale``,
``mc_error_shape`` and ``mc_error_depth_gain`` metadata).

The stack-consistency stage weighs each network pose by its expected error. MC dropout measures
the network's uncertainty, not its error: the two differ by a factor, the ratio of their root mean
squares (the shipped model's is in docs/consistency.md). This module measures that ratio on
single validation slices and writes it into the ONNX file's metadata (weights untouched), where
:class:`service.inference.model_file.ModelInfo` reads it.

The error is not alike in the six coordinates of a slice either
(:mod:`service.consistency.error_shape`). Its shape is measured on what the stack-consistency
stage weighs, the slices of simulated stacks through the validation volumes (with motion, so each
slice sits at its own tilt): single slices at any orientation have a far less certain twist than
a stack's near-standard planes, so a shape measured on them would mis-weigh the stage's slices.
The same acquisitions give the errors' growth towards a stack's ends beyond their spread
(``mc_error_depth_gain``).

Example (with the atlas at hand):
    >>> scale = measure_error_scale(Path("service/models/default/model.onnx"))   # doctest: +SKIP
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx

from model_export.acquisitions import simulate_acquisition
from model_export.atlas import DEFAULT_ATLAS_ROOT, held_out_volumes, split, validation_volumes
from model_export.evaluate_acquisitions import MIN_MASK_PIXELS, prepare_acquisition
from model_export.export import metadata_of, set_metadata
from model_export.simulate import SimulationConfig
from model_export.train import validation_set
from service.consistency.error_shape import depth_gain, error_coordinates, error_shape, relative_depth
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
    _, val_names = split(root, validation_volumes(info.metadata))
    cfg = SimulationConfig.validation(size=info.input_size, pixel_mm=info.pixel_spacing_mm)
    val = validation_set(val_names, root, per_volume, seed=seed, config=cfg)
    est = OnnxPoseEstimator(model).estimate(val.inputs, mc_samples)
    plane = info.symmetry_plane_x_mm
    err = twin.twin_min_ed(est.mean, val.poses, plane)
    return {"slices": len(err), "twin_min_ed_rms_mm": float(np.sqrt(np.mean(err ** 2))),
            "spread_rms_mm": float(np.sqrt(np.mean(est.spread_mm ** 2))),
            "mc_error_scale": error_scale(err, est.spread_mm)}


def measure_error_shape(model_path: Path, root: Path = DEFAULT_ATLAS_ROOT, per_volume: int = 2,
                        mc_samples: int = 100, seed: int = 777, motion: str = "mild") -> dict[str, object]:
    """The shape of the model's error (:func:`~service.consistency.error_shape.error_shape`) and its
    growth towards a stack's outer slices (:func:`~service.consistency.error_shape.depth_gain`) on the
    slices with >= 20 mask pixels of ``per_volume`` simulated 3-stack acquisitions of each validation
    volume (``seed``: another stream than the evaluation's), each against the nearer of the truth
    and its twin, in units of its expected error."""
    model = load_model(model_path)
    info = model.info
    estimator = OnnxPoseEstimator(model)
    volumes = held_out_volumes(info.metadata, root)
    rng, coords, spread, depth = np.random.default_rng(seed), [], [], []
    for vol in volumes:
        for _ in range(per_volume):
            prepared, truths = prepare_acquisition(simulate_acquisition(vol.image, vol.mask, vol.affine, rng, motion), info)
            truth = np.concatenate(truths)
            inside = np.concatenate([p.prepared.mask_pixels for p in prepared]) >= MIN_MASK_PIXELS
            depth.append(np.concatenate([relative_depth(np.arange(len(p.prepared.inputs), dtype=float),
                                                        p.prepared.mask_pixels >= MIN_MASK_PIXELS)
                                         for p in prepared])[inside])
            est = estimator.estimate(np.concatenate([p.prepared.inputs for p in prepared]), mc_samples)
            coords.append(error_coordinates(est.mean, twin.nearer(est.mean, truth, info.symmetry_plane_x_mm))[inside])
            spread.append(est.spread_mm[inside])
    coords, spread, depth = np.concatenate(coords), np.concatenate(spread), np.concatenate(depth)
    shape = error_shape(coords, spread)
    return {"stack_slices": len(coords), "mc_error_shape": [float(f"{x:.4g}") for x in shape],
            "mc_error_depth_gain": depth_gain(coords, spread, depth)}


SPREAD_FLAGS = ("mc_error_scale", "mc_error_shape", "mc_error_depth_gain")
"""What :func:`calibrate_spread` writes, under the names of the model's metadata the service reads."""


def calibrate_spread(model_path: Path, root: Path = DEFAULT_ATLAS_ROOT, per_volume: int = 60,
                     write: bool = True) -> dict[str, object]:
    """Measure the model's ``mc_error_scale`` (:func:`measure_error_scale`), ``mc_error_shape`` and
    ``mc_error_depth_gain`` (:func:`measure_error_shape`) and, with ``write``, store them in its metadata:
    what every later stage's expected error, and so the accept flags, are calibrated on.

    Example (with the atlas at hand):
        >>> calibrate_spread(Path("model.onnx"), write=False)["mc_error_scale"]   # doctest: +SKIP
        0.68
    """
    result = measure_error_scale(model_path, root, per_volume) | measure_error_shape(model_path, root)
    if write:
        write_metadata(model_path, {"mc_error_scale": f"{result['mc_error_scale']:.3f}",
                                    "mc_error_shape": ",".join(f"{x:.4g}" for x in result["mc_error_shape"]),
                                    "mc_error_depth_gain": f"{result['mc_error_depth_gain']:.2f}"})
    return result


def write_metadata(model_path: Path, updates: dict[str, object]) -> None:
    """Set ``updates`` in the ONNX file's metadata (values as strings), the graph untouched."""
    proto = onnx.load(str(model_path))
    set_metadata(proto, {**metadata_of(proto), **updates})
    onnx.save(proto, str(model_path))
