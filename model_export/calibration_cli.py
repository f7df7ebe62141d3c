"""``svrnet-train``'s calibrations: the variance threshold, the MC spread, the accept flags, the
noise error and the frame error (registered on the app by :mod:`model_export.cli`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer

from model_export.atlas import DEFAULT_ATLAS_ROOT
from model_export.cli_options import PoseCheckpoint, PoseModel, ValidationRoot, pose_model
from service.inference.views import SHIPPED_VIEWS


KeptSlices = Annotated[Optional[Path], typer.Option(help="also keep every slice's columns here (.npz)")]
KeptColumns = Annotated[Optional[list[Path]], typer.Option(
    help="calibrate from the slice columns previous runs kept (--slices) instead of measuring again; "
         "given several times, their slices pooled")]
"""The options of a calibration measured on slice columns (the accept flags, the noise and frame errors)."""


def calibrate(checkpoint: PoseCheckpoint, root: ValidationRoot = DEFAULT_ATLAS_ROOT, mc_samples: int = 100,
              tta_views: int = SHIPPED_VIEWS,
              model: Annotated[Optional[Path], typer.Option(
                  callback=pose_model,
                  help="the ONNX file exported from CHECKPOINT to measure as the service runs it (its own views; "
                       "int8 where quantised) [default: CHECKPOINT's float network with --tta-views]")] = None) -> None:
    """Choose the variance threshold on the checkpoint's validation volumes; print AUROC and the chosen value."""
    from model_export.calibrate import calibrate as run

    result = run(checkpoint, root, mc_samples=mc_samples, views=tta_views, model_file=model)
    typer.echo(json.dumps({k: v for k, v in result.items() if not isinstance(v, list)}, indent=2))


def calibrate_spread(
    model: PoseModel,
    root: ValidationRoot = DEFAULT_ATLAS_ROOT,
    per_volume: int = 60,
    write: Annotated[bool, typer.Option(help="write mc_error_scale, mc_error_shape and mc_error_depth_gain into the model's metadata")] = True,
) -> None:
    """Measure how the model's MC spread relates to its twin-min error (mc_error_scale), and the error's
    shape over the six coordinates of a slice (mc_error_shape) and its growth towards a stack's outer
    slices (mc_error_depth_gain); store them."""
    from model_export.spread import calibrate_spread as run

    typer.echo(json.dumps(run(model, root, per_volume, write), indent=2))
    if write:
        typer.echo("the accept flags (expected-error limit, floor, twin risk, variance threshold), the noise error and "
                   "the frame error were calibrated on the expected errors before: run `calibrate-acceptance`, then "
                   "`calibrate-noise`, then `calibrate-frame`, on the model again", err=True)


def calibrate_acceptance(
    model: PoseModel,
    root: ValidationRoot = DEFAULT_ATLAS_ROOT,
    per_volume: Annotated[Optional[int], typer.Option(help="acquisitions per validation volume and motion level "
                                                           "(default: calibrate_acceptance.PER_VOLUME)")] = None,
    report: Annotated[Optional[Path], typer.Option(help="markdown report (default: acceptance.md beside the model; "
                                                        "the shipped model's is model_export/reports/acceptance.md)")] = None,
    write: Annotated[bool, typer.Option(help="write twin_risk_logit, expected_error_floor_mm, variance_threshold "
                                             "and max_expected_error_mm into the model's metadata")] = True,
    seed: int = 1,
    slices: KeptSlices = None,
    columns: KeptColumns = None,
) -> None:
    """Calibrate the accept flags on the pipeline's final poses over simulated acquisitions of the
    model's validation volumes (its metadata's) at every motion level (mild, moderate, jumps, independent)."""
    from model_export.atlas import held_out_volumes
    from model_export.calibrate_acceptance import LEVELS, PER_VOLUME, calibrate, flag_metadata, level_columns, markdown, measure
    from model_export.spread import write_metadata
    from service.inference.estimator import OnnxPoseEstimator
    from service.inference.model_file import load_model

    if columns:
        result = calibrate(level_columns(columns, LEVELS))
    else:
        loaded = load_model(model)
        result = measure(OnnxPoseEstimator(loaded), held_out_volumes(loaded.info.metadata, root),
                         per_volume or PER_VOLUME, seed, slices=slices)
    report = report or model.with_name("acceptance.md")        # never the shipped model's report by default
    report.parent.mkdir(parents=True, exist_ok=True)
    report.write_text(markdown(result, f"Accept flags of {model}"))
    if write:
        write_metadata(model, flag_metadata(result))
    typer.echo(json.dumps(result, indent=2))


def calibrate_noise(
    model: PoseModel,
    root: ValidationRoot = DEFAULT_ATLAS_ROOT,
    per_volume: Annotated[Optional[int], typer.Option(help="acquisitions per validation volume, noise level, pixel size "
                                                           "and motion level (default: calibrate_noise.PER_VOLUME)")] = None,
    report: Annotated[Optional[Path], typer.Option(help="markdown report (default: noise.md beside the model; "
                                                        "the shipped model's is model_export/reports/noise.md)")] = None,
    write: Annotated[bool, typer.Option(help="write noise_error into the model's metadata")] = True,
    seed: int = 7,
    slices: KeptSlices = None,
    columns: KeptColumns = None,
) -> None:
    """Calibrate how the expected errors grow with a stack's input noise (noise_error) on simulated
    acquisitions of the model's validation volumes (its metadata's) at a ladder of noise levels and
    two pixel sizes."""
    from model_export import calibrate_noise as noise

    hinge_calibration(model, root, report or model.with_name("noise.md"), write, slices, columns,
                      ("ed", "expected", "input_noise"), noise, noise.noise_metadata, "Noise calibration",
                      lambda estimator, volumes: noise.measure(estimator, volumes, per_volume or noise.PER_VOLUME, seed))


def calibrate_frame(
    model: PoseModel,
    root: ValidationRoot = DEFAULT_ATLAS_ROOT,
    per_volume: Annotated[Optional[int], typer.Option(help="acquisitions per validation volume and motion level "
                                                           "(default: calibrate_frame.PER_VOLUME)")] = None,
    scenes: Annotated[Optional[int], typer.Option(help="whole-uterus requests of three stacks, each sent without "
                                                       "masks and with the atlas's (default: calibrate_frame.SCENES)")] = None,
    report: Annotated[Optional[Path], typer.Option(help="markdown report (default: frame.md beside the model; "
                                                        "the shipped model's is model_export/reports/frame.md)")] = None,
    write: Annotated[bool, typer.Option(help="write frame_error into the model's metadata")] = True,
    seed: int = 11,
    scene_seed: Annotated[int, typer.Option(help="the first whole-uterus request's seed")] = 2_400_000,
    slices: KeptSlices = None,
    columns: KeptColumns = None,
) -> None:
    """Calibrate how a request's frame error grows with the network's error on its slices (frame_error)
    on simulated acquisitions and whole-uterus requests of the model's validation volumes."""
    from model_export import calibrate_frame as frame

    hinge_calibration(model, root, report or model.with_name("frame.md"), write, slices, columns, ("ed", "expected", "sigma"),
                      frame, frame.frame_metadata, "Frame-error calibration",
                      lambda estimator, volumes: frame.measure(estimator, volumes, per_volume or frame.PER_VOLUME, seed,
                                                               frame.SCENES if scenes is None else scenes, scene_seed))


def hinge_calibration(model: Path, root: Path, report: Path, write: bool, slices: Optional[Path],
                      columns: Optional[list[Path]], keys: tuple[str, ...], module, metadata, title: str,  # noqa: ANN001
                      measure) -> None:  # noqa: ANN001
    """A hinge calibration's command (``calibrate-noise``, ``calibrate-frame``): the slice columns
    ``keys`` measured on the model's validation volumes by ``measure(estimator, volumes)`` (kept in
    ``slices``) or pooled from earlier runs' ``columns``; ``module.calibrate`` and ``module.markdown``
    of them; the report written to ``report`` under ``title``, the model's metadata (``metadata`` of
    the result) with ``write``; the result printed."""
    import numpy as np

    from model_export.atlas import held_out_volumes
    from model_export.spread import write_metadata
    from service.inference.estimator import OnnxPoseEstimator
    from service.inference.model_file import load_model

    if columns:
        measured = pooled_columns(columns, keys)
    else:
        loaded = load_model(model)
        measured = measure(OnnxPoseEstimator(loaded), held_out_volumes(loaded.info.metadata, root))
        if slices is not None:
            np.savez_compressed(slices, **measured)
    result = module.calibrate(measured)
    report.parent.mkdir(parents=True, exist_ok=True)                   # never the shipped model's report by default
    report.write_text(f"# {title} of {model}\n\n{module.markdown(result)}\n")
    if write:
        write_metadata(model, metadata(result))
    typer.echo(json.dumps(result, indent=2))


def pooled_columns(paths: list[Path], keys: tuple[str, ...]) -> dict:
    """The slice columns ``keys`` that earlier runs kept (``--slices``: one ``.npz`` each), their slices pooled."""
    import numpy as np

    parts = []
    for path in paths:
        with np.load(path) as kept:
            parts.append({k: kept[k] for k in keys})
    return {k: np.concatenate([p[k] for p in parts]) for k in keys}


COMMANDS = {"calibrate": calibrate, "calibrate-spread": calibrate_spread, "calibrate-acceptance": calibrate_acceptance,
            "calibrate-noise": calibrate_noise, "calibrate-frame": calibrate_frame}
"""Each command's name and function (:mod:`model_export.cli` registers them first, so ``svrnet-train
--help`` lists them before its own)."""
