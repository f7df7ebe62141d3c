"""A tiny untrained pose network with non-trivial batch-norm statistics, for export and quantisation tests."""

from __future__ import annotations

from collections.abc import Iterable

import torch

from model_export.model import SVRNet


def tiny_pose_model(size: int, batches: Iterable[torch.Tensor]) -> SVRNet:
    """A width-0.25 ``compact`` anchor network (eval mode) whose batch norms saw ``batches`` (so that
    exporting batch norm in training mode, or a quantiser's calibration, would show)."""
    torch.manual_seed(0)
    model = SVRNet("compact", 0.25, "anchor", size, hidden=64, dropout=0.5)
    model.train()
    with torch.no_grad():
        for x in batches:
            model.features(x)
    model.set_label_normalisation(torch.randn(100, 9) * 40 + 5)
    return model.eval()
