"""VGG trunk (Simonyan & Zisserman, 2015).

Stacks of 3x3 convolutions separated by 2x2 max pooling, in the VGG-11 (configuration A) or
VGG-16 (configuration D) layout, with batch normalisation after every convolution (the "_bn"
variants). The three fully connected layers and their dropout are left to the regression head.

Spatial size for a 96-px slice: 96 -> 48 -> 24 -> 12 -> 6 -> 3 (five max pools).
"""

from __future__ import annotations

from torch import nn

from ._blocks import Backbone, ConvBNReLU, init_weights

__all__ = ["VGG", "VGG_CONFIGS"]

#: Layer configurations: an int is a 3x3 conv with that many channels (width 1.0), "M" a max pool.
VGG_CONFIGS: dict[str, tuple[int | str, ...]] = {
    "vgg11": (64, "M", 128, "M", 256, 256, "M", 512, 512, "M", 512, 512, "M"),
    "vgg16": (
        64, 64, "M",
        128, 128, "M",
        256, 256, 256, "M",
        512, 512, 512, "M",
        512, 512, 512, "M",
    ),
}


class VGG(Backbone):
    """VGG-11/16 convolutional trunk for 1-channel slices.

    Args:
        width: Channel multiplier; every channel count is scaled and rounded to a multiple of 8.
        config: ``"vgg16"`` (default, 13 convolutions) or ``"vgg11"`` (8 convolutions).

    Attributes:
        out_features: Length of the output feature vector (512 at width 1.0).

    Raises:
        ValueError: If ``config`` is unknown.
    """

    def __init__(self, width: float = 1.0, *, config: str = "vgg16") -> None:
        super().__init__(width)
        if config not in VGG_CONFIGS:
            raise ValueError(f"unknown VGG config {config!r}; choose from {sorted(VGG_CONFIGS)}")
        layers: list[nn.Module] = []
        in_ch = 1
        for item in VGG_CONFIGS[config]:
            if item == "M":
                layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
            else:
                out_ch = self.ch(int(item))
                layers.append(ConvBNReLU(in_ch, out_ch, kernel_size=3))
                in_ch = out_ch
        self.config = config
        self.features = nn.Sequential(*layers)
        self.out_features = in_ch
        init_weights(self)
