"""Checkpoints <-> models: rebuild an :class:`SVRNet` from a checkpoint, export it with its metadata."""

from __future__ import annotations

from pathlib import Path

import torch

from model_export.atlas import ATLAS_ID, HELD_OUT, POPULATIONS, validation_volumes
from model_export.calibrate_acceptance import FLAGS
from model_export.calibrate_frame import FRAME_FLAGS
from model_export.calibrate_noise import NOISE_FLAGS
from model_export.export import build_metadata, export_onnx, fix_draws
from model_export.model import SVRNet
from model_export.spread import SPREAD_FLAGS
from service.inference.views import SHIPPED_VIEWS

CALIBRATION = (*SPREAD_FLAGS, *FLAGS, *NOISE_FLAGS, *FRAME_FLAGS)
"""A model's calibrated metadata: the spread's (``calibrate-spread``), then the accept flags'
(``calibrate-acceptance``), then the noise error's (``calibrate-noise``) and the frame error's
(``calibrate-frame``); the rest of its metadata is the network's own."""


def load_checkpoint(path: Path) -> tuple[SVRNet, dict]:
    """The model (eval mode) and the whole checkpoint dict."""
    ck = torch.load(path, map_location="cpu", weights_only=False)
    return SVRNet.from_checkpoint(ck), ck


def export_checkpoint(checkpoint: Path, output: Path, *, name: str, version: str,
                      variance_threshold: float, tta_views: int = SHIPPED_VIEWS, extra: dict | None = None) -> Path:
    """Export a training checkpoint to ONNX with the metadata the service reads, its dropout draws
    fed by the service (:func:`~model_export.export.fix_draws`); the service runs it with
    ``tta_views`` test-time views (:mod:`service.inference.views`; without the field it would run one).
    Its ``validation_volumes`` (comma-separated) are the checkpoint's, on which every later
    calibration and evaluation of the file runs (:func:`~model_export.atlas.validation_volumes`)."""
    model, ck = load_checkpoint(checkpoint)
    cfg = ck["config"]
    held_out = validation_volumes(ck)
    training = (f"{len(cfg['train_volumes'])} atlas volumes ({', '.join(cfg['train_volumes'])}); "
                f"{HELD_OUT}{', '.join(held_out)}")
    meta = build_metadata(
        model, name=name, version=version, pixel_mm=ck["simulation"]["pixel_mm"],
        variance_threshold=variance_threshold, atlas_id=ATLAS_ID, training_data=training,
        licences="; ".join(POPULATIONS.values()), symmetry_plane_x_mm=float(cfg.get("plane_x_mm", 0.0)),
        extra={"train_steps": ck["step"], "samples_seen": ck["samples_seen"],
               "train_loss": cfg.get("loss", "l2"), "tta_views": tta_views, "validation_volumes": ",".join(held_out),
               **(extra or {})},
    )
    path = export_onnx(model, output, meta)
    fix_draws(path)
    return path
