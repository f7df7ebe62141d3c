"""Inception-v4 trunk (Szegedy et al., 2017), with reduced depth.

The Inception-v4 stem (three 3x3 convolutions and three split-and-concatenate "mixed" blocks),
then Inception-A blocks, Reduction-A, Inception-B blocks (factorised 1x7/7x1 convolutions),
Reduction-B and Inception-C blocks (split 1x3/3x1 outputs), with the paper's channel counts
(384 / 1024 / 1536 at width 1.0). The paper stacks 4/7/3 blocks; the default here is 2/4/2 to keep
training on small data sets tractable (pass ``depths=(4, 7, 3)`` for the full network).

All convolutions use "same" padding (the paper uses some "valid" ones), so that any input size
from 64 px works and every stride-2 step maps ``L`` to ``ceil(L / 2)``. Spatial size for a
96-px slice: 96 -> 48 (stem conv) -> 24 (mixed 3a) -> 12 (mixed 5a) -> 6 (reduction A) -> 3
(reduction B). Dropout and the classifier are left to the regression head.
"""

from __future__ import annotations

import torch
from torch import nn

from ._blocks import Backbone, ConvBNReLU, init_weights, max_pool_3x3_s2, scale_channels

__all__ = [
    "InceptionA",
    "InceptionB",
    "InceptionC",
    "InceptionV4",
    "ReductionA",
    "ReductionB",
    "Stem",
]


def _avg_pool_3x3() -> nn.AvgPool2d:
    """3x3 / stride-1 average pooling that ignores the zero padding."""
    return nn.AvgPool2d(kernel_size=3, stride=1, padding=1, count_include_pad=False)


class _Concat(nn.Module):
    """Runs parallel branches on one input and concatenates their outputs along channels.

    Args:
        branches: The parallel branches.
        out_channels: Total channels of the concatenation.
    """

    def __init__(self, branches: list[nn.Module], out_channels: int) -> None:
        super().__init__()
        self.branches = nn.ModuleList(branches)
        self.out_channels = out_channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Concatenates ``[branch(x) for branch in branches]`` along dim 1.

        Args:
            x: Feature map ``[B, C, H, W]``.

        Returns:
            Feature map ``[B, out_channels, H', W']``.
        """
        return torch.cat([branch(x) for branch in self.branches], dim=1)


class Stem(nn.Sequential):
    """Inception-v4 stem: 1 channel to 384 channels (width 1.0), 1/8 of the input size.

    Args:
        width: Channel multiplier.

    Attributes:
        out_channels: Output channels.
    """

    def __init__(self, width: float) -> None:
        def ch(c: int) -> int:
            return scale_channels(c, width)

        c32, c64, c96, c192 = ch(32), ch(64), ch(96), ch(192)
        convs = nn.Sequential(
            ConvBNReLU(1, c32, 3, stride=2),
            ConvBNReLU(c32, c32, 3),
            ConvBNReLU(c32, c64, 3),
        )
        mixed_3a = _Concat([max_pool_3x3_s2(), ConvBNReLU(c64, c96, 3, stride=2)], c64 + c96)
        c = mixed_3a.out_channels
        mixed_4a = _Concat(
            [
                nn.Sequential(ConvBNReLU(c, c64, 1), ConvBNReLU(c64, c96, 3)),
                nn.Sequential(
                    ConvBNReLU(c, c64, 1),
                    ConvBNReLU(c64, c64, (1, 7)),
                    ConvBNReLU(c64, c64, (7, 1)),
                    ConvBNReLU(c64, c96, 3),
                ),
            ],
            2 * c96,
        )
        c = mixed_4a.out_channels
        mixed_5a = _Concat([ConvBNReLU(c, c192, 3, stride=2), max_pool_3x3_s2()], c192 + c)
        super().__init__(convs, mixed_3a, mixed_4a, mixed_5a)
        self.out_channels = mixed_5a.out_channels


class InceptionA(_Concat):
    """Inception-A block (35x35 grid in the paper): 384 channels at width 1.0.

    Args:
        in_channels: Input channels.
        width: Channel multiplier.
    """

    def __init__(self, in_channels: int, width: float) -> None:
        c64, c96 = scale_channels(64, width), scale_channels(96, width)
        super().__init__(
            [
                ConvBNReLU(in_channels, c96, 1),
                nn.Sequential(ConvBNReLU(in_channels, c64, 1), ConvBNReLU(c64, c96, 3)),
                nn.Sequential(
                    ConvBNReLU(in_channels, c64, 1), ConvBNReLU(c64, c96, 3), ConvBNReLU(c96, c96, 3)
                ),
                nn.Sequential(_avg_pool_3x3(), ConvBNReLU(in_channels, c96, 1)),
            ],
            4 * c96,
        )


class ReductionA(_Concat):
    """Reduction-A block: halves the grid, 384 -> 1024 channels at width 1.0.

    Args:
        in_channels: Input channels.
        width: Channel multiplier.
    """

    def __init__(self, in_channels: int, width: float) -> None:
        # (k, l, m, n) of the paper's table 1 for Inception-v4.
        k, l_, m, n = (scale_channels(c, width) for c in (192, 224, 256, 384))
        super().__init__(
            [
                ConvBNReLU(in_channels, n, 3, stride=2),
                nn.Sequential(
                    ConvBNReLU(in_channels, k, 1), ConvBNReLU(k, l_, 3), ConvBNReLU(l_, m, 3, stride=2)
                ),
                max_pool_3x3_s2(),
            ],
            n + m + in_channels,
        )


class InceptionB(_Concat):
    """Inception-B block (17x17 grid in the paper) with factorised 7x7 convolutions.

    Args:
        in_channels: Input channels.
        width: Channel multiplier.
    """

    def __init__(self, in_channels: int, width: float) -> None:
        c128, c192, c224, c256, c384 = (scale_channels(c, width) for c in (128, 192, 224, 256, 384))
        super().__init__(
            [
                ConvBNReLU(in_channels, c384, 1),
                nn.Sequential(
                    ConvBNReLU(in_channels, c192, 1),
                    ConvBNReLU(c192, c224, (1, 7)),
                    ConvBNReLU(c224, c256, (7, 1)),
                ),
                nn.Sequential(
                    ConvBNReLU(in_channels, c192, 1),
                    ConvBNReLU(c192, c192, (7, 1)),
                    ConvBNReLU(c192, c224, (1, 7)),
                    ConvBNReLU(c224, c224, (7, 1)),
                    ConvBNReLU(c224, c256, (1, 7)),
                ),
                nn.Sequential(_avg_pool_3x3(), ConvBNReLU(in_channels, c128, 1)),
            ],
            c384 + 2 * c256 + c128,
        )


class ReductionB(_Concat):
    """Reduction-B block: halves the grid, 1024 -> 1536 channels at width 1.0.

    Args:
        in_channels: Input channels.
        width: Channel multiplier.
    """

    def __init__(self, in_channels: int, width: float) -> None:
        c192, c256, c320 = (scale_channels(c, width) for c in (192, 256, 320))
        super().__init__(
            [
                nn.Sequential(ConvBNReLU(in_channels, c192, 1), ConvBNReLU(c192, c192, 3, stride=2)),
                nn.Sequential(
                    ConvBNReLU(in_channels, c256, 1),
                    ConvBNReLU(c256, c256, (1, 7)),
                    ConvBNReLU(c256, c320, (7, 1)),
                    ConvBNReLU(c320, c320, 3, stride=2),
                ),
                max_pool_3x3_s2(),
            ],
            c192 + c320 + in_channels,
        )


class _SplitConv(nn.Module):
    """A 1x3 and a 3x1 convolution on the same input, concatenated (Inception-C outputs).

    Args:
        in_channels: Input channels.
        out_channels: Channels of each of the two convolutions.
    """

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv_1x3 = ConvBNReLU(in_channels, out_channels, (1, 3))
        self.conv_3x1 = ConvBNReLU(in_channels, out_channels, (3, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Returns ``cat([conv_1x3(x), conv_3x1(x)])`` along channels.

        Args:
            x: Feature map ``[B, in_channels, H, W]``.

        Returns:
            Feature map ``[B, 2 * out_channels, H, W]``.
        """
        return torch.cat([self.conv_1x3(x), self.conv_3x1(x)], dim=1)


class InceptionC(_Concat):
    """Inception-C block (8x8 grid in the paper): 1536 channels at width 1.0.

    Args:
        in_channels: Input channels.
        width: Channel multiplier.
    """

    def __init__(self, in_channels: int, width: float) -> None:
        c256, c384, c448, c512 = (scale_channels(c, width) for c in (256, 384, 448, 512))
        super().__init__(
            [
                ConvBNReLU(in_channels, c256, 1),
                nn.Sequential(ConvBNReLU(in_channels, c384, 1), _SplitConv(c384, c256)),
                nn.Sequential(
                    ConvBNReLU(in_channels, c384, 1),
                    ConvBNReLU(c384, c448, (3, 1)),
                    ConvBNReLU(c448, c512, (1, 3)),
                    _SplitConv(c512, c256),
                ),
                nn.Sequential(_avg_pool_3x3(), ConvBNReLU(in_channels, c256, 1)),
            ],
            6 * c256,
        )


class InceptionV4(Backbone):
    """Inception-v4 convolutional trunk for 1-channel slices.

    Args:
        width: Channel multiplier; every channel count is scaled and rounded to a multiple of 8.
        depths: Number of Inception-A, -B and -C blocks; the paper uses ``(4, 7, 3)``.

    Attributes:
        out_features: Length of the output feature vector (1536 at width 1.0).

    Raises:
        ValueError: If a depth is negative.
    """

    def __init__(self, width: float = 1.0, *, depths: tuple[int, int, int] = (2, 4, 2)) -> None:
        super().__init__(width)
        if any(d < 0 for d in depths):
            raise ValueError(f"depths must be non-negative, got {depths!r}")
        stem = Stem(width)
        layers: list[nn.Module] = [stem]
        c = stem.out_channels
        stages: tuple[tuple[type[_Concat], int, type[_Concat] | None], ...] = (
            (InceptionA, depths[0], ReductionA),
            (InceptionB, depths[1], ReductionB),
            (InceptionC, depths[2], None),
        )
        for block, depth, reduction in stages:
            for _ in range(depth):
                module = block(c, width)
                layers.append(module)
                c = module.out_channels
            if reduction is not None:
                module = reduction(c, width)
                layers.append(module)
                c = module.out_channels
        self.features = nn.Sequential(*layers)
        self.out_features = c
        init_weights(self)
