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
    """On a GPU: TF32 matrix products and convolutions (the usual setting for training a CNN; nothing
    changes on a CPU). cuDNN's benchmarked choice of algorithms stays off: it picks by timing, and a
    run would no longer give the same weights on the same kind of device."""
    if torch.device(device).type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
