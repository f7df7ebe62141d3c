"""A narrower localiser taught by the shipped one: channel-pruned start, mirrored-ensemble targets.

The service's localiser runs its network twice a slice (the slice and its mirror image, logits
averaged: :attr:`service.preprocess.localise.Localiser.mirrored`). A student of fewer channels
learns that average in one pass:

* :func:`pruned` starts it from the teacher's weights: at every level it keeps the channels whose
  batch-norm scales are largest (a channel whose scale is near 0 carries little), so the student
  begins near the teacher rather than from noise;
* :func:`mirrored_logits` is the target: the teacher's logits of a batch averaged with those of the
  batch mirrored along its last axis, as the service computes them;
* :func:`distillation_loss` mixes binary cross-entropy against the teacher's probabilities with
  :func:`~model_export.localiser.train.loss_fn` against the generated scene's true mask, so the
  student keeps the teacher's behaviour on what the scenes do not label (real faces, bodies)
  and still sees the truth.

Example:
    >>> import torch
    >>> teacher = LocaliserNet(width=8, depth=2).eval()
    >>> student = pruned(teacher, width=6)
    >>> student.config["width"], student(torch.zeros(1, 3, 32, 32)).shape
    (6, torch.Size([1, 1, 32, 32]))
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

from model_export.localiser.net import LocaliserNet


def _kept(bn: nn.BatchNorm2d, count: int) -> torch.Tensor:
    """Indices of the ``count`` channels with the largest ``|gamma|``, in their original order."""
    return torch.sort(torch.topk(bn.weight.detach().abs(), count).indices).values


def _copy_block(src: nn.Sequential, dst: nn.Sequential, cin: torch.Tensor, cout: torch.Tensor) -> None:
    """Copy a conv-BN-ReLU x 2 block, keeping input channels ``cin``, output channels ``cout`` and the
    middle channels whose first batch norm weighs most."""
    mid = _kept(src[1], dst[1].num_features)
    with torch.no_grad():
        for conv, bn, ins, outs in ((0, 1, cin, mid), (3, 4, mid, cout)):
            dst[conv].weight.copy_(src[conv].weight[outs][:, ins])
            for name in ("weight", "bias", "running_mean", "running_var"):
                getattr(dst[bn], name).copy_(getattr(src[bn], name)[outs])


def pruned(teacher: LocaliserNet, width: int) -> LocaliserNet:
    """A :class:`LocaliserNet` of ``width`` whose weights are ``teacher``'s at its strongest channels.

    Each level keeps the channels the batch norm of its encoder block's output weighs most; the
    decoder's merge block at that level keeps the same channels, its input being the up-sampled
    channels followed by the skip's.
    """
    depth = teacher.config["depth"]
    student = LocaliserNet(in_channels=teacher.config["in_channels"], width=width, depth=depth)
    sizes = [student.down[i][0].out_channels for i in range(depth + 1)]
    teacher_sizes = [teacher.down[i][0].out_channels for i in range(depth + 1)]
    keep = [_kept(teacher.down[i][4], sizes[i]) for i in range(depth + 1)]
    inputs = torch.arange(teacher.config["in_channels"])
    for i in range(depth + 1):
        _copy_block(teacher.down[i], student.down[i], inputs if i == 0 else keep[i - 1], keep[i])
    with torch.no_grad():
        for i in range(depth):
            up_t, up_s = teacher.up[i], student.up[i]       # ConvTranspose2d weight: [in, out, k, k]
            up_s.weight.copy_(up_t.weight[keep[i + 1]][:, keep[i]])
            up_s.bias.copy_(up_t.bias[keep[i]])
            merged = torch.cat([keep[i], keep[i] + teacher_sizes[i]])
            _copy_block(teacher.merge[i], student.merge[i], merged, keep[i])
        student.head.weight.copy_(teacher.head.weight[:, keep[0]])
        student.head.bias.copy_(teacher.head.bias)
    return student


@torch.no_grad()
def mirrored_logits(teacher: LocaliserNet, x: torch.Tensor) -> torch.Tensor:
    """The teacher's logits of ``x`` averaged with those of ``x`` mirrored along its last axis
    (mirrored back): what the service's mirrored pass computes."""
    return 0.5 * (teacher(x) + teacher(x.flip(-1)).flip(-1))


def distillation_loss(logits: torch.Tensor, teacher_logits: torch.Tensor, target: torch.Tensor,
                      teacher_weight: float, loss_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                      ) -> torch.Tensor:
    """``teacher_weight`` x BCE against the teacher's probabilities + the rest x ``loss_fn`` against
    the true brain fraction."""
    soft = F.binary_cross_entropy_with_logits(logits, torch.sigmoid(teacher_logits))
    return teacher_weight * soft + (1.0 - teacher_weight) * loss_fn(logits, target)
