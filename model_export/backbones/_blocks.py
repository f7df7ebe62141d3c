"""Shared building blocks for the convolutional trunks.

Everything here is plain PyTorch and restricted to operators that export cleanly to ONNX
(opset 17, ``dynamo=False``): ``Conv2d``, ``BatchNorm2d``, ``ReLU``, pooling, ``cat`` and ``add``.
No dropout and no fully connected layers live in a trunk; those belong to the regression head.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = [
    "Backbone",
    "ConvBN",
    "ConvBNReLU",
    "GlobalAvgPool",
    "init_weights",
    "max_pool_3x3_s2",
    "scale_channels",
]

IntPair = int | tuple[int, int]


def scale_channels(channels: int, width: float) -> int:
    """Scales a channel count by ``width`` and rounds it to a multiple of 8.

    Args:
        channels: Channel count of the reference (width 1.0) architecture.
        width: Width multiplier, must be positive.

    Returns:
        ``channels * width`` rounded to the nearest multiple of 8, at least 8.

    Raises:
        ValueError: If ``width`` is not positive.
    """
    if not width > 0:
        raise ValueError(f"width must be positive, got {width!r}")
    return max(8, int(channels * width / 8.0 + 0.5) * 8)


def _same_padding(kernel_size: IntPair) -> tuple[int, int]:
    """Returns the padding that keeps the spatial size for stride 1 (odd kernels)."""
    kh, kw = (kernel_size, kernel_size) if isinstance(kernel_size, int) else kernel_size
    return kh // 2, kw // 2


class ConvBN(nn.Sequential):
    """``Conv2d`` (no bias) followed by ``BatchNorm2d``, without activation.

    Used as the last layer of a residual branch, where the ReLU follows the addition.

    Args:
        in_channels: Input channels.
        out_channels: Output channels.
        kernel_size: Kernel size, an int or ``(kh, kw)``.
        stride: Convolution stride.
        padding: Explicit padding; ``None`` means "same" padding for odd kernels, which gives an
            output of ``ceil(L / stride)`` pixels.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: IntPair = 3,
        stride: int = 1,
        padding: IntPair | None = None,
    ) -> None:
        pad = _same_padding(kernel_size) if padding is None else padding
        super().__init__(
            nn.Conv2d(in_channels, out_channels, kernel_size, stride=stride, padding=pad, bias=False),
            nn.BatchNorm2d(out_channels),
        )


class ConvBNReLU(nn.Sequential):
    """``Conv2d`` (no bias), ``BatchNorm2d`` and ``ReLU``: the basic unit of every trunk.

    Args:
        in_channels: Input channels.
        out_channels: Output channels.
        kernel_size: Kernel size, an int or ``(kh, kw)``.
        stride: Convolution stride.
        padding: Explicit padding; ``None`` means "same" padding for odd kernels.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: IntPair = 3,
        stride: int = 1,
        padding: IntPair | None = None,
    ) -> None:
        pad = _same_padding(kernel_size) if padding is None else padding
        super().__init__(
            nn.Conv2d(in_channels, out_channels, kernel_size, stride=stride, padding=pad, bias=False),
            nn.BatchNorm2d(out_channels),
            nn.ReLU(inplace=True),
        )


def max_pool_3x3_s2() -> nn.MaxPool2d:
    """Overlapping 3x3 / stride-2 max pooling with padding 1.

    The padding makes the output ``ceil(L / 2)`` pixels for any ``L``, so the pooled map matches a
    stride-2 "same" convolution (needed where both feed one concatenation) and never collapses to
    zero pixels on small inputs.

    Returns:
        The pooling module.
    """
    return nn.MaxPool2d(kernel_size=3, stride=2, padding=1)


class GlobalAvgPool(nn.Module):
    """Global average pooling to a ``[B, C]`` feature vector (ONNX ``GlobalAveragePool``)."""

    def __init__(self) -> None:
        super().__init__()
        self.pool = nn.AdaptiveAvgPool2d(1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Pools ``[B, C, H, W]`` to ``[B, C]``.

        Args:
            x: Feature map ``[B, C, H, W]``.

        Returns:
            Feature vector ``[B, C]``.
        """
        return torch.flatten(self.pool(x), 1)


def init_weights(module: nn.Module) -> None:
    """Initialises convolutions (He, fan-out) and batch norms (unit scale, zero shift) in place.

    Args:
        module: Root module; all sub-modules are visited.
    """
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)


class Backbone(nn.Module):
    """Base class of every trunk: ``features`` followed by global average pooling.

    Subclasses build ``self.features`` (mapping ``[B, 1, L, L]`` to ``[B, C, h, w]``) and set
    ``self.out_features = C`` in their constructor, then call :func:`init_weights`.

    Attributes:
        features: The convolutional trunk.
        pool: Global average pooling.
        out_features: Length of the output feature vector.
        width: The width multiplier the trunk was built with.
    """

    features: nn.Module
    out_features: int

    def __init__(self, width: float = 1.0) -> None:
        super().__init__()
        scale_channels(8, width)  # validates width
        self.width = float(width)
        self.pool = GlobalAvgPool()

    def ch(self, channels: int) -> int:
        """Scales a reference channel count by this trunk's width.

        Args:
            channels: Channel count at width 1.0.

        Returns:
            The scaled count (multiple of 8, at least 8).
        """
        return scale_channels(channels, self.width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Maps a batch of slices to feature vectors.

        Args:
            x: Float tensor ``[B, 1, L, L]``.

        Returns:
            Float tensor ``[B, out_features]``.
        """
        return self.pool(self.features(x))
