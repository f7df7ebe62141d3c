"""CaffeNet (AlexNet-style) trunk.

Five convolutions with a large, strided first kernel and overlapping max pooling, after
Krizhevsky et al. (2012) in its single-tower Caffe form (Jia et al., 2014). Local response
normalisation is replaced by batch normalisation, the grouped convolutions by dense ones, and the
fully connected layers (and their dropout) are left to the regression head.

Spatial size for a 96-px slice: 96 -> 24 (conv1, stride 4) -> 12 -> 6 -> 3 (three max pools).
"""

from __future__ import annotations

from torch import nn

from ._blocks import Backbone, ConvBNReLU, init_weights, max_pool_3x3_s2

__all__ = ["CaffeNet"]


class CaffeNet(Backbone):
    """CaffeNet/AlexNet convolutional trunk for 1-channel slices.

    Layers (channels at width 1.0): conv 11x11/4 (96), pool, conv 5x5 (256), pool,
    conv 3x3 (384), conv 3x3 (384), conv 3x3 (256), pool, global average pool.

    Args:
        width: Channel multiplier; every channel count is scaled and rounded to a multiple of 8.

    Attributes:
        out_features: Length of the output feature vector (256 at width 1.0).
    """

    def __init__(self, width: float = 1.0) -> None:
        super().__init__(width)
        c1, c2, c3, c4, c5 = (self.ch(c) for c in (96, 256, 384, 384, 256))
        self.features = nn.Sequential(
            ConvBNReLU(1, c1, kernel_size=11, stride=4, padding=5),  # conv1
            max_pool_3x3_s2(),  # pool1
            ConvBNReLU(c1, c2, kernel_size=5),  # conv2
            max_pool_3x3_s2(),  # pool2
            ConvBNReLU(c2, c3, kernel_size=3),  # conv3
            ConvBNReLU(c3, c4, kernel_size=3),  # conv4
            ConvBNReLU(c4, c5, kernel_size=3),  # conv5
            max_pool_3x3_s2(),  # pool5
        )
        self.out_features = c5
        init_weights(self)
