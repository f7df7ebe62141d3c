"""A small 2.5D U-Net: three neighbouring slices in, the middle slice's brain logit out.

The network is fully convolutional; its input side must be a multiple of ``2 ** depth``
(:data:`service.preprocess.localise.PAD_MULTIPLE`), which the service's input function guarantees.

Example:
    >>> import torch
    >>> net = LocaliserNet(width=4, depth=3)
    >>> net(torch.zeros(2, 3, 32, 48)).shape
    torch.Size([2, 1, 32, 48])
"""

from __future__ import annotations

import torch
from torch import nn


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
    )


class LocaliserNet(nn.Module):
    """U-Net of ``depth`` poolings; level ``l`` has ``width * 2 ** l`` channels (at most ``8 * width``)."""

    def __init__(self, in_channels: int = 3, width: int = 8, depth: int = 4) -> None:
        super().__init__()
        chans = [min(width * 2 ** level, 8 * width) for level in range(depth + 1)]
        self.config = {"in_channels": in_channels, "width": width, "depth": depth}
        self.down = nn.ModuleList([_block(in_channels, chans[0])] +
                                  [_block(chans[i], chans[i + 1]) for i in range(depth)])
        self.up = nn.ModuleList([nn.ConvTranspose2d(chans[i + 1], chans[i], 2, stride=2) for i in range(depth)])
        self.merge = nn.ModuleList([_block(2 * chans[i], chans[i]) for i in range(depth)])
        self.head = nn.Conv2d(chans[0], 1, 1)
        self.pool = nn.MaxPool2d(2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        for i, block in enumerate(self.down):
            x = block(x if i == 0 else self.pool(x))
            skips.append(x)
        x = skips.pop()
        for i in reversed(range(len(self.up))):
            x = self.merge[i](torch.cat([self.up[i](x), skips[i]], dim=1))
        return self.head(x)
