"""Network-in-Network (NIN) trunk.

Mlpconv blocks, each a spatial convolution followed by two 1x1 convolutions (the "micro
network"), separated by max pooling and ending in global average pooling (Lin et al., 2014), in
the layout of the ImageNet model of the Caffe model zoo. The final 1x1 convolution keeps 1024
channels instead of producing class scores: the regression head follows the trunk. Batch
normalisation follows every convolution; the dropout of the original lives in the head.

Spatial size for a 96-px slice: 96 -> 24 (stride 4) -> 12 -> 6 -> 3 (three max pools).
"""

from __future__ import annotations

from torch import nn

from ._blocks import Backbone, ConvBNReLU, init_weights, max_pool_3x3_s2

__all__ = ["MlpConv", "NIN"]


class MlpConv(nn.Sequential):
    """One mlpconv block: a k x k convolution followed by ``n_1x1`` 1x1 convolutions.

    Args:
        in_channels: Input channels.
        out_channels: Channels of every convolution in the block.
        kernel_size: Kernel of the spatial convolution.
        stride: Stride of the spatial convolution.
        padding: Padding of the spatial convolution; ``None`` means "same".
        n_1x1: Number of 1x1 convolutions after the spatial one.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int,
        stride: int = 1,
        padding: int | None = None,
        n_1x1: int = 2,
    ) -> None:
        layers: list[nn.Module] = [
            ConvBNReLU(in_channels, out_channels, kernel_size, stride=stride, padding=padding)
        ]
        layers += [ConvBNReLU(out_channels, out_channels, kernel_size=1) for _ in range(n_1x1)]
        super().__init__(*layers)


class NIN(Backbone):
    """Network-in-Network trunk for 1-channel slices.

    Four mlpconv blocks (channels at width 1.0): 11x11/4 (96), 5x5 (256), 3x3 (384), 3x3 (1024),
    with 3x3/2 max pooling after the first three, then global average pooling.

    Args:
        width: Channel multiplier; every channel count is scaled and rounded to a multiple of 8.

    Attributes:
        out_features: Length of the output feature vector (1024 at width 1.0).
    """

    def __init__(self, width: float = 1.0) -> None:
        super().__init__(width)
        c1, c2, c3, c4 = (self.ch(c) for c in (96, 256, 384, 1024))
        self.features = nn.Sequential(
            MlpConv(1, c1, kernel_size=11, stride=4, padding=5),
            max_pool_3x3_s2(),
            MlpConv(c1, c2, kernel_size=5),
            max_pool_3x3_s2(),
            MlpConv(c2, c3, kernel_size=3),
            max_pool_3x3_s2(),
            MlpConv(c3, c4, kernel_size=3),
        )
        self.out_features = c4
        init_weights(self)
