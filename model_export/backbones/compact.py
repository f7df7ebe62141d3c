"""Compact default trunk, sized for CPU training and inference.

Five stride-2 3x3 conv-BN-ReLU stages (32-64-96-128-192 channels at width 1.0) with a one-conv
residual refinement at the 24, 12 and 6 px scales, then a 1x1 expansion to 256 channels and global
average pooling. For a 96-px slice the grid goes 96 -> 48 -> 24 -> 12 -> 6 -> 3.

At width 1.0 the trunk has about 0.7 M parameters and costs about 65 M multiply-adds
(~0.13 GFLOP) per 96x96 slice, so a 2-core CPU runs several hundred slices per second.
"""

from __future__ import annotations

import torch
from torch import nn

from ._blocks import Backbone, ConvBN, ConvBNReLU, init_weights

__all__ = ["CompactNet", "ResidualConv"]

#: Output channels of the stride-2 stages at width 1.0.
STAGE_CHANNELS: tuple[int, ...] = (32, 64, 96, 128, 192)
#: Whether each stage ends with a residual 3x3 convolution.
STAGE_RESIDUAL: tuple[bool, ...] = (False, True, True, True, False)
#: Channels of the final 1x1 expansion at width 1.0.
OUT_CHANNELS: int = 256


class ResidualConv(nn.Module):
    """One 3x3 conv-BN with an identity shortcut: ``relu(x + bn(conv(x)))``.

    The BatchNorm scale starts at zero, so the block is initially the identity.

    Args:
        channels: Input and output channels.
    """

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.branch = ConvBN(channels, channels, kernel_size=3)
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Applies the block.

        Args:
            x: Feature map ``[B, channels, H, W]``.

        Returns:
            Feature map of the same shape.
        """
        return self.relu(x + self.branch(x))


class CompactNet(Backbone):
    """Compact CPU-friendly trunk for 1-channel slices (the default backbone).

    Args:
        width: Channel multiplier; every channel count is scaled and rounded to a multiple of 8.

    Attributes:
        out_features: Length of the output feature vector (256 at width 1.0).
    """

    def __init__(self, width: float = 1.0) -> None:
        super().__init__(width)
        layers: list[nn.Module] = []
        in_ch = 1
        for channels, residual in zip(STAGE_CHANNELS, STAGE_RESIDUAL):
            out_ch = self.ch(channels)
            layers.append(ConvBNReLU(in_ch, out_ch, kernel_size=3, stride=2))
            if residual:
                layers.append(ResidualConv(out_ch))
            in_ch = out_ch
        out_ch = self.ch(OUT_CHANNELS)
        layers.append(ConvBNReLU(in_ch, out_ch, kernel_size=1))
        self.features = nn.Sequential(*layers)
        self.out_features = out_ch
        init_weights(self)
        for m in self.modules():
            if isinstance(m, ResidualConv):
                nn.init.zeros_(m.branch[1].weight)
