"""Readers: uploaded files -> :class:`~service.io.volume.Volume` (array ``[i, j, k]`` + RAS affine)."""

from service.io.volume import Volume, read_volume, write_volume

__all__ = ["Volume", "read_volume", "write_volume"]
