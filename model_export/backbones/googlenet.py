"""GoogLeNet (Inception-v1) trunk (Szegedy et al., 2015).

The stem (7x7/2 convolution, max pool, 1x1 and 3x3 convolutions, max pool) followed by nine
Inception modules (3a-3b, 4a-4e, 5a-5b) with max pooling after 3b and 4e. Every module has the four
original branches: 1x1; 1x1 -> 3x3; 1x1 -> 5x5; 3x3 max pool -> 1x1. Batch normalisation follows
each convolution (as in the BN-Inception re-implementations); LRN, the auxiliary classifiers,
dropout and the final classifier are omitted (the head lives elsewhere).

Spatial size for a 96-px slice: 96 -> 48 -> 24 -> 12 -> 6 -> 3 (stride-2 conv plus four pools).
"""

from __future__ import annotations

import torch
from torch import nn

from ._blocks import Backbone, ConvBNReLU, init_weights, max_pool_3x3_s2

__all__ = ["GoogLeNet", "InceptionV1", "INCEPTION_V1_CONFIGS"]

#: Channels of the Inception modules at width 1.0 (Szegedy et al., table 1):
#: (1x1, 3x3 reduce, 3x3, 5x5 reduce, 5x5, pool projection). ``"M"`` is a 3x3/2 max pool.
INCEPTION_V1_CONFIGS: tuple[tuple[int, int, int, int, int, int] | str, ...] = (
    (64, 96, 128, 16, 32, 32),  # 3a -> 256
    (128, 128, 192, 32, 96, 64),  # 3b -> 480
    "M",
    (192, 96, 208, 16, 48, 64),  # 4a -> 512
    (160, 112, 224, 24, 64, 64),  # 4b -> 512
    (128, 128, 256, 24, 64, 64),  # 4c -> 512
    (112, 144, 288, 32, 64, 64),  # 4d -> 528
    (256, 160, 320, 32, 128, 128),  # 4e -> 832
    "M",
    (256, 160, 320, 32, 128, 128),  # 5a -> 832
    (384, 192, 384, 48, 128, 128),  # 5b -> 1024
)


class InceptionV1(nn.Module):
    """Inception (v1) module with four parallel branches concatenated along channels.

    Args:
        in_channels: Input channels.
        c1x1: Channels of the 1x1 branch.
        c3x3_reduce: Channels of the 1x1 reduction before the 3x3 convolution.
        c3x3: Channels of the 3x3 branch.
        c5x5_reduce: Channels of the 1x1 reduction before the 5x5 convolution.
        c5x5: Channels of the 5x5 branch.
        pool_proj: Channels of the 1x1 projection after the 3x3 max pool.

    Attributes:
        out_channels: ``c1x1 + c3x3 + c5x5 + pool_proj``.
    """

    def __init__(
        self,
        in_channels: int,
        c1x1: int,
        c3x3_reduce: int,
        c3x3: int,
        c5x5_reduce: int,
        c5x5: int,
        pool_proj: int,
    ) -> None:
        super().__init__()
        self.branch1 = ConvBNReLU(in_channels, c1x1, kernel_size=1)
        self.branch2 = nn.Sequential(
            ConvBNReLU(in_channels, c3x3_reduce, kernel_size=1),
            ConvBNReLU(c3x3_reduce, c3x3, kernel_size=3),
        )
        self.branch3 = nn.Sequential(
            ConvBNReLU(in_channels, c5x5_reduce, kernel_size=1),
            ConvBNReLU(c5x5_reduce, c5x5, kernel_size=5),
        )
        self.branch4 = nn.Sequential(
            nn.MaxPool2d(kernel_size=3, stride=1, padding=1),
            ConvBNReLU(in_channels, pool_proj, kernel_size=1),
        )
        self.out_channels = c1x1 + c3x3 + c5x5 + pool_proj

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Applies the four branches and concatenates them.

        Args:
            x: Feature map ``[B, in_channels, H, W]``.

        Returns:
            Feature map ``[B, out_channels, H, W]``.
        """
        return torch.cat([self.branch1(x), self.branch2(x), self.branch3(x), self.branch4(x)], dim=1)


class GoogLeNet(Backbone):
    """GoogLeNet convolutional trunk for 1-channel slices.

    Args:
        width: Channel multiplier; every channel count is scaled and rounded to a multiple of 8.

    Attributes:
        out_features: Length of the output feature vector (1024 at width 1.0).
    """

    def __init__(self, width: float = 1.0) -> None:
        super().__init__(width)
        c_stem1, c_stem2, c_stem3 = self.ch(64), self.ch(64), self.ch(192)
        layers: list[nn.Module] = [
            ConvBNReLU(1, c_stem1, kernel_size=7, stride=2),
            max_pool_3x3_s2(),
            ConvBNReLU(c_stem1, c_stem2, kernel_size=1),
            ConvBNReLU(c_stem2, c_stem3, kernel_size=3),
            max_pool_3x3_s2(),
        ]
        in_ch = c_stem3
        for cfg in INCEPTION_V1_CONFIGS:
            if cfg == "M":
                layers.append(max_pool_3x3_s2())
                continue
            assert not isinstance(cfg, str)
            module = InceptionV1(in_ch, *(self.ch(c) for c in cfg))
            layers.append(module)
            in_ch = module.out_channels
        self.features = nn.Sequential(*layers)
        self.out_features = in_ch
        init_weights(self)
