"""The device a training run steps on, set up for speed.

Example:
    >>> resolve_device("cpu")
    device(type='cpu')
"""

from __future__ import annotations

import torch


def resolve_device(name: str) -> torch.device:
    """``auto`` -> ``cuda`` when available, else ``cpu``; on ``cuda``, :func:`fast_cuda`."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(name)
    fast_cuda(device)
    return device


def fast_cuda(device: torch.device | str) -> None:
    """On a GPU: TF32 matrix products and convolutions, and cuDNN's fastest algorithm for the
    network's fixed input shapes (found once). Both are the usual settings for training a CNN;
    neither changes what runs on a CPU."""
    if torch.device(device).type == "cuda":
        torch.backends.cudnn.benchmark = True
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
