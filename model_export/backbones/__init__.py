"""Convolutional trunks of the networks compared in the SVRnet paper, plus a compact default.

Every trunk maps a batch of 1-channel slices ``[B, 1, L, L]`` (``L`` from 64 to 160 px) to a
feature vector ``[B, out_features]`` after global average pooling, contains no dropout and no
fully connected layers (those belong to the regression head), takes a ``width`` multiplier for all
channel counts, and exports to ONNX (opset 17) with a dynamic batch dimension.

Example:
    >>> from model_export.backbones import build_backbone
    >>> net = build_backbone("compact", width=0.5)
    >>> net.out_features
    128
"""

from __future__ import annotations

from collections.abc import Callable

from torch import nn

from ._blocks import Backbone, scale_channels
from .caffenet import CaffeNet
from .compact import CompactNet
from .googlenet import GoogLeNet
from .inception_v4 import InceptionV4
from .nin import NIN
from .resnet import ResNet
from .vgg import VGG

__all__ = [
    "BACKBONES",
    "Backbone",
    "CaffeNet",
    "CompactNet",
    "DEFAULT_BACKBONE",
    "GoogLeNet",
    "InceptionV4",
    "NIN",
    "ResNet",
    "VGG",
    "build_backbone",
    "scale_channels",
]

#: Registry of trunk constructors, each called as ``constructor(width=...)``.
BACKBONES: dict[str, Callable[..., nn.Module]] = {
    "caffenet": CaffeNet,
    "googlenet": GoogLeNet,
    "inception_v4": InceptionV4,
    "nin": NIN,
    "resnet": ResNet,
    "vgg": VGG,
    "compact": CompactNet,
}

#: The trunk used when none is named: sized for CPU training and inference.
DEFAULT_BACKBONE: str = "compact"


def build_backbone(name: str, width: float = 1.0) -> nn.Module:
    """Builds a trunk by registry name.

    Args:
        name: One of the keys of :data:`BACKBONES`.
        width: Channel multiplier (every channel count is scaled and rounded to a multiple of 8).

    Returns:
        The trunk, with an int attribute ``out_features``.

    Raises:
        ValueError: If ``name`` is not a registered backbone, or ``width`` is not positive.
    """
    try:
        constructor = BACKBONES[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown backbone {name!r}; valid choices: {', '.join(sorted(BACKBONES))}"
        ) from None
    return constructor(width=width)
