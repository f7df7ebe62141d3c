"""SVRnet: a convolutional trunk, a multi-branch regression head with MC dropout.

* Input: slices ``[B, 1, L, L]`` with 0-255 intensities (the service's preprocessing); the network
  maps them to ``[-1, 1]`` itself, so every consumer feeds the same thing.
* Head (Gal & Ghahramani): dropout before EVERY fully connected layer -- a shared FC layer, then one
  FC branch per label component (the multi-loss framework: one branch and one L2 loss per anchor
  point, or per rotation/translation part).
* Output: labels in physical units (mm / radians); the normalisation of the targets (mean and
  scale of each component over training labels) is a buffer of the model, undone in the graph.

:meth:`SVRNet.mc_forward` is the export path: the trunk runs once per slice and the head ``N`` times
on the repeated features, with dropout masks drawn by ``rand_like`` (ONNX ``RandomUniformLike``,
which onnxruntime's optimiser cannot remove, unlike ``Dropout``). ``passes`` is a vector whose
length is ``N`` and whose entries switch dropout on (1) or off (0) for each pass, so one graph does
both the deterministic pass (``passes = [0]``) and MC sampling (``passes = ones(N)``).
"""

from __future__ import annotations

import torch
from torch import nn

from model_export.backbones import build_backbone
from service.geometry import encodings


class PoseHead(nn.Module):
    """Shared FC layer and one FC branch per label component, each preceded by dropout."""

    def __init__(self, in_features: int, label_type: str, hidden: int = 256, p: float = 0.5) -> None:
        super().__init__()
        self.encoding = encodings.get(label_type)
        self.p = float(p)
        self.shared = nn.Linear(in_features, hidden)
        self.branches = nn.ModuleList(
            nn.Linear(hidden, sl.stop - sl.start) for _, sl in self.encoding.branches
        )

    def forward(self, features: torch.Tensor, drop) -> torch.Tensor:  # noqa: ANN001 - a callable
        h = torch.relu(self.shared(drop(features)))
        h = drop(h)
        return torch.cat([b(h) for b in self.branches], dim=-1)


class SVRNet(nn.Module):
    """Backbone + :class:`PoseHead`; outputs labels ``[B, D]`` of ``label_type`` in physical units."""

    def __init__(self, backbone: str = "compact", width: float = 1.0, label_type: str = "anchor",
                 input_size: int = 96, hidden: int = 256, dropout: float = 0.5, spatial_grid: int = 3,
                 grid_channels: int = 0) -> None:
        super().__init__()
        self.config = dict(backbone=backbone, width=width, label_type=label_type, input_size=input_size,
                           hidden=hidden, dropout=dropout, spatial_grid=spatial_grid, grid_channels=grid_channels)
        self.trunk = build_backbone(backbone, width)
        # Pose needs WHERE features are: keep a coarse spatial grid of the last feature map instead
        # of global pooling (0 = the trunk's global average pooling). Plain average pooling (which
        # ONNX exports) when the map divides into the grid, else the map as it is. ``grid_channels``
        # first reduces the map by a 1x1 convolution (part of the trunk, run once per slice), so the
        # head -- the part MC dropout repeats -- stays small: 32 channels x 3 x 3 = 288 features
        # instead of 2304 makes the 100 head passes cheaper than the trunk.
        self.grid: nn.Module | None = None
        if spatial_grid:
            with torch.no_grad():
                fmap = self.trunk.features(torch.zeros(1, 1, input_size, input_size))
            m = fmap.shape[-1]
            pool = nn.AvgPool2d(m // spatial_grid) if m >= spatial_grid and m % spatial_grid == 0 else nn.Identity()
            reduce = [nn.Conv2d(fmap.shape[1], grid_channels, 1), nn.ReLU(inplace=True)] if grid_channels else []
            self.grid = nn.Sequential(*reduce, pool)
        with torch.no_grad():
            n_features = self.features(torch.zeros(1, 1, input_size, input_size)).shape[1]
        self.head = PoseHead(n_features, label_type, hidden, dropout)
        size = encodings.get(label_type).size
        self.register_buffer("label_mean", torch.zeros(size))
        self.register_buffer("label_scale", torch.ones(size))

    @classmethod
    def from_checkpoint(cls, ck: dict) -> "SVRNet":
        """The network of a checkpoint dict (``model_config`` and ``model``), in eval mode; a
        checkpoint without ``spatial_grid`` pools globally."""
        model = cls(**{"spatial_grid": 0, **ck["model_config"]})
        model.load_state_dict(ck["model"])
        return model.eval()

    @property
    def label_type(self) -> str:
        return self.config["label_type"]

    def set_label_normalisation(self, labels: torch.Tensor) -> None:
        """Centre and scale each output on a sample of training labels ``[N, D]``."""
        self.label_mean.copy_(labels.mean(0))
        self.label_scale.copy_(labels.std(0).clamp_min(1e-3))

    def features(self, slices: torch.Tensor) -> torch.Tensor:
        x = slices / 127.5 - 1.0
        if self.grid is None:
            return self.trunk(x)
        return torch.flatten(self.grid(self.trunk.features(x)), 1)

    def normalised(self, slices: torch.Tensor) -> torch.Tensor:
        """Normalised outputs (training target space); dropout follows ``self.training``."""
        drop = lambda x: nn.functional.dropout(x, self.head.p, self.training)  # noqa: E731
        return self.head(self.features(slices), drop)

    def forward(self, slices: torch.Tensor) -> torch.Tensor:
        return self.normalised(slices) * self.label_scale + self.label_mean

    def mc_forward(self, slices: torch.Tensor, passes: torch.Tensor) -> torch.Tensor:
        """Labels ``[B, N, D]``: trunk once, head ``N = len(passes)`` times with MC dropout masks."""
        feats = self.features(slices)                                     # [B, F]
        n = passes.shape[0]
        feats = feats.unsqueeze(1).expand(-1, n, -1)                      # [B, N, F]
        on = (passes > 0.5).to(feats.dtype).reshape(1, -1, 1)          # [1, N, 1]
        p = self.head.p

        def drop(x: torch.Tensor) -> torch.Tensor:
            # One mask per pass, shared by the slices of the batch: N networks drawn from the
            # approximate posterior, each applied to every slice (per slice the same statistics as
            # independent masks, and the random draw costs N x F instead of B x N x F).
            keep = (torch.rand_like(x[:1]) >= p).to(x.dtype)
            return x * (on * keep / (1.0 - p) + (1.0 - on))

        return self.head(feats, drop) * self.label_scale + self.label_mean


class MCExport(nn.Module):
    """The module that is exported to ONNX: ``(slices, passes) -> labels [B, N, D]``."""

    def __init__(self, model: SVRNet) -> None:
        super().__init__()
        self.model = model

    def forward(self, slices: torch.Tensor, passes: torch.Tensor) -> torch.Tensor:
        return self.model.mc_forward(slices, passes)


def multi_loss(pred: torch.Tensor, target: torch.Tensor, label_type: str,
               weights: tuple[float, ...] | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """The paper's multi-loss: ``sum_b w_b || pred_b - target_b ||_2`` over branches, batch mean.

    As in the paper, a quaternion label keeps its scalar part non-negative, so two rotations on either
    side of 180 degrees lie far apart in the label (about 2 in the quaternion's branch) though they
    are near: the quaternion and Euler labels are the paper's baselines; the anchor and grid labels,
    continuous in the pose, are what the service's models learn.

    Returns the total and each branch's mean L2 (for logging).
    """
    enc = encodings.get(label_type)
    weights = weights or (1.0,) * len(enc.branches)
    total = pred.new_zeros(())
    parts = {}
    for w, (name, sl) in zip(weights, enc.branches):
        d = torch.linalg.vector_norm(pred[:, sl] - target[:, sl], dim=1).mean()
        total = total + w * d
        parts[name] = float(d.detach())
    return total, parts
