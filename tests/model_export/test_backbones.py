"""Tests for the convolutional trunks in ``model_export.backbones``."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from model_export.backbones import BACKBONES, build_backbone, scale_channels

NAMES = sorted(BACKBONES)
SMALL = 0.25

#: ONNX operators a trunk may export to (BatchNormalization is usually folded into Conv).
ALLOWED_OPS = {
    "Add",
    "AveragePool",
    "BatchNormalization",
    "Concat",
    "Conv",
    "Flatten",
    "GlobalAveragePool",
    "Identity",
    "MaxPool",
    "ReduceMean",
    "Relu",
}


def _calibrate(net: nn.Module, size: int = 96) -> nn.Module:
    """Gives every BatchNorm non-trivial affine parameters and batch statistics, then evals.

    Without this, the default (zero-mean, unit-variance, some zero-scale) BatchNorms make the eval
    graph nearly trivial and the ONNX comparison weaker.
    """
    gen = torch.Generator().manual_seed(0)
    for m in net.modules():
        if isinstance(m, nn.BatchNorm2d):
            with torch.no_grad():
                m.weight.copy_(0.5 + torch.rand(m.weight.shape, generator=gen))
                m.bias.copy_(0.2 * torch.randn(m.bias.shape, generator=gen))
            m.momentum = 1.0  # running stats := statistics of the next batch
    net.train()
    with torch.no_grad():
        net(torch.randn(8, 1, size, size, generator=gen))
    return net.eval()


@pytest.fixture(autouse=True)
def _single_thread() -> Iterator[None]:
    """Runs each test single-threaded: these nets are tiny, and on a shared 2-core machine
    OpenMP barriers across busy cores cost far more than the parallelism gains."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


@pytest.mark.parametrize("name", NAMES)
def test_forward_shapes_and_gradients(name: str) -> None:
    torch.manual_seed(0)
    net = build_backbone(name, width=SMALL)
    assert isinstance(net.out_features, int) and net.out_features > 0
    assert net.out_features % 8 == 0

    net.train()
    x = torch.randn(2, 1, 96, 96, requires_grad=True)
    out = net(x)
    assert out.shape == (2, net.out_features)
    assert torch.isfinite(out).all()
    out.square().mean().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()

    net.eval()
    with torch.no_grad():
        for size in (96, 120):
            out = net(torch.randn(2, 1, size, size))
            assert out.shape == (2, net.out_features)
            assert torch.isfinite(out).all()


@pytest.mark.parametrize("name", NAMES)
def test_trunk_has_no_dropout_or_fc_and_width_scales(name: str) -> None:
    net = build_backbone(name, width=SMALL)
    bad = [m for m in net.modules() if isinstance(m, (nn.Linear, nn.Dropout, nn.Dropout2d))]
    assert not bad
    for m in net.modules():
        if isinstance(m, nn.Conv2d):
            assert m.out_channels % 8 == 0 and m.out_channels >= 8
    wide = BACKBONES[name](width=0.5)
    assert wide.out_features > net.out_features


def test_scale_channels() -> None:
    assert scale_channels(64, 1.0) == 64
    assert scale_channels(64, 0.25) == 16
    assert scale_channels(16, 0.25) == 8  # minimum
    assert scale_channels(100, 1.0) == 104  # nearest multiple of 8
    with pytest.raises(ValueError):
        scale_channels(64, 0.0)


def test_compact_is_small() -> None:
    net = build_backbone("compact")
    n_params = sum(p.numel() for p in net.parameters())
    assert n_params < 2_000_000
    assert net.out_features == 256


def test_unknown_backbone_raises() -> None:
    with pytest.raises(ValueError, match="compact"):
        build_backbone("nope")


@pytest.mark.parametrize("name", NAMES)
def test_onnx_export_matches_torch(name: str, tmp_path: Path) -> None:
    onnx = pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    torch.manual_seed(0)
    net = _calibrate(build_backbone(name, width=SMALL))
    path = tmp_path / f"{name}.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(
            net,
            (torch.randn(2, 1, 96, 96),),
            str(path),
            dynamo=False,
            opset_version=17,
            input_names=["slices"],
            output_names=["features"],
            dynamic_axes={"slices": {0: "batch"}, "features": {0: "batch"}},
        )
    model = onnx.load(str(path))
    onnx.checker.check_model(model)
    ops = {node.op_type for node in model.graph.node}
    assert ops <= ALLOWED_OPS, f"unexpected ONNX ops: {sorted(ops - ALLOWED_OPS)}"

    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    x = torch.randn(3, 1, 96, 96)
    with torch.no_grad():
        expected = net(x).numpy()
    (got,) = session.run(None, {"slices": x.numpy()})
    assert got.shape == (3, net.out_features)
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-4)
