"""ResNet-18 trunk (He et al., 2016).

A 7x7/2 stem with 3x3/2 max pooling, then four stages of two basic blocks (two 3x3 convolutions
with an identity or 1x1 projection shortcut), 64-128-256-512 channels at width 1.0, the last three
stages starting with stride 2. The final BatchNorm of every residual branch starts at zero scale
(Goyal et al., 2017), so each block is initially the identity.

Spatial size for a 96-px slice: 96 -> 48 (stem) -> 24 (pool) -> 24 -> 12 -> 6 -> 3.
"""

from __future__ import annotations

import torch
from torch import nn

from ._blocks import Backbone, ConvBN, ConvBNReLU, init_weights, max_pool_3x3_s2

__all__ = ["BasicBlock", "ResNet"]


class BasicBlock(nn.Module):
    """ResNet basic block: ``relu(branch(x) + shortcut(x))``.

    Args:
        in_channels: Input channels.
        out_channels: Output channels.
        stride: Stride of the first convolution (and of the projection shortcut).
    """

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1) -> None:
        super().__init__()
        self.branch = nn.Sequential(
            ConvBNReLU(in_channels, out_channels, kernel_size=3, stride=stride),
            ConvBN(out_channels, out_channels, kernel_size=3),
        )
        if stride != 1 or in_channels != out_channels:
            self.shortcut: nn.Module = ConvBN(in_channels, out_channels, kernel_size=1, stride=stride)
        else:
            self.shortcut = nn.Identity()
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Applies the block.

        Args:
            x: Feature map ``[B, in_channels, H, W]``.

        Returns:
            Feature map ``[B, out_channels, ceil(H / stride), ceil(W / stride)]``.
        """
        return self.relu(self.branch(x) + self.shortcut(x))


class ResNet(Backbone):
    """ResNet-18 convolutional trunk for 1-channel slices.

    Args:
        width: Channel multiplier; every channel count is scaled and rounded to a multiple of 8.
        blocks: Basic blocks per stage; ``(2, 2, 2, 2)`` is ResNet-18, ``(3, 4, 6, 3)`` ResNet-34.

    Attributes:
        out_features: Length of the output feature vector (512 at width 1.0).
    """

    def __init__(self, width: float = 1.0, *, blocks: tuple[int, int, int, int] = (2, 2, 2, 2)) -> None:
        super().__init__(width)
        stem_ch = self.ch(64)
        layers: list[nn.Module] = [
            ConvBNReLU(1, stem_ch, kernel_size=7, stride=2),
            max_pool_3x3_s2(),
        ]
        in_ch = stem_ch
        for stage, (channels, n_blocks) in enumerate(zip((64, 128, 256, 512), blocks)):
            out_ch = self.ch(channels)
            for i in range(n_blocks):
                stride = 2 if (stage > 0 and i == 0) else 1
                layers.append(BasicBlock(in_ch, out_ch, stride=stride))
                in_ch = out_ch
        self.features = nn.Sequential(*layers)
        self.out_features = in_ch
        init_weights(self)
        for m in self.modules():
            if isinstance(m, BasicBlock):
                nn.init.zeros_(m.branch[-1][1].weight)
