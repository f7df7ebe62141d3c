"""The localiser's training batches from synthetic shards (:mod:`model_export.localiser.dataset`).

A batch draws slices (most of them crossing the brain), rebuilds their 2.5D channels as the
service does (a slice between its neighbours, the ends repeated), crops a window that holds the
brain's centre where the slice has brain, turns and flips it, and varies its contrast in the ways
the input function's percentile scaling does not undo (:func:`vary_contrast`).

Example:
    >>> rng = np.random.default_rng(0)
    >>> shard = Shard(np.ones((3, 40, 40), np.float16), np.zeros((3, 40, 40), np.uint8), np.array([], int))
    >>> x, y = draw_batch([shard], rng, batch=2, crop=32)
    >>> x.shape, y.shape, float(y.max())
    ((2, 3, 32, 32), (2, 1, 32, 32), 0.0)
"""

from __future__ import annotations

import sys
import time
import zipfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage


@dataclass
class Shard:
    slices: np.ndarray          # [n, H, W] float16
    target: np.ndarray          # [n, H, W] uint8
    brain: np.ndarray           # indices of slices with brain
    grid_mm: float | None = None  # the network grid the shard was made on (None: a shard from before it was recorded)


def _read_new(folder: Path, known: dict, read) -> dict:  # noqa: ANN001
    """``known`` with ``read(npz)`` of every whole shard of ``folder`` not in it yet (a shard still
    being written is skipped: it is read on a later call)."""
    for path in sorted(Path(folder).glob("*.npz")):
        if path.name in known:
            continue
        try:
            with np.load(path) as z:
                known[path.name] = read(z)
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            continue
    return known


def _grid_of(z) -> float | None:  # noqa: ANN001
    return float(z["grid_mm"]) if "grid_mm" in z else None


def load_shards(folder: Path, known: dict[str, Shard]) -> dict[str, Shard]:
    """Every shard of ``folder`` (those already in ``known`` are kept, not read again)."""
    def shard(z) -> Shard:  # noqa: ANN001
        t = z["target"]
        return Shard(z["slices"], t, np.flatnonzero(t.reshape(len(t), -1).max(1) > 127), _grid_of(z))

    return _read_new(folder, known, shard)


def shards_grid_mm(shards: dict[str, Shard]) -> float | None:
    """The network grid all ``shards`` were made on (None where none records it).

    Raises:
        ValueError: the shards were made on different grids (a network learns one grid).
    """
    return one_grid_mm(s.grid_mm for s in shards.values())


def one_grid_mm(grids: Iterable[float | None]) -> float | None:
    found = sorted({g for g in grids if g is not None})
    if len(found) > 1:
        raise ValueError(f"the shards were made on grids of {found} mm: train on shards of one grid")
    return found[0] if found else None


def draw_batch(shards: list[Shard], rng: np.random.Generator, batch: int, crop: int,
               brain_share: float = 0.75) -> tuple[np.ndarray, np.ndarray]:
    """``[B, 3, crop, crop]`` inputs and ``[B, 1, crop, crop]`` targets (0..1)."""
    xs = np.zeros((batch, 3, crop, crop), np.float32)
    ys = np.zeros((batch, 1, crop, crop), np.float32)
    for b in range(batch):
        s = shards[int(rng.integers(len(shards)))]
        n, h, w = s.slices.shape
        with_brain = len(s.brain) > 0 and rng.random() < brain_share
        k = int(rng.choice(s.brain)) if with_brain else int(rng.integers(n))
        idx = np.clip([k - 1, k, k + 1], 0, n - 1)
        x = s.slices[idx].astype(np.float32)
        y = s.target[k].astype(np.float32) / 255.0
        if with_brain:
            rows, cols = np.nonzero(y > 0.5)
            cr, cc = (rows.mean(), cols.mean()) if len(rows) else (h / 2, w / 2)
            r0 = int(np.clip(cr - crop / 2 + rng.uniform(-0.35, 0.35) * crop, 0, max(0, h - crop)))
            c0 = int(np.clip(cc - crop / 2 + rng.uniform(-0.35, 0.35) * crop, 0, max(0, w - crop)))
        else:
            r0, c0 = int(rng.integers(max(1, h - crop + 1))), int(rng.integers(max(1, w - crop + 1)))
        x, y = x[:, r0:r0 + crop, c0:c0 + crop], y[r0:r0 + crop, c0:c0 + crop]
        turns, flip = int(rng.integers(4)), rng.random() < 0.5
        x, y = np.rot90(x, turns, (1, 2)), np.rot90(y, turns)
        if flip:
            x, y = x[:, :, ::-1], y[:, ::-1]
        if rng.random() < 0.5:
            x = x[::-1]                                # the slice order reversed
        x = vary_contrast(np.ascontiguousarray(x), rng)
        xs[b, :, :x.shape[1], :x.shape[2]] = x
        ys[b, 0, :y.shape[0], :y.shape[1]] = y
    return xs, ys


class BatchStream(torch.utils.data.IterableDataset):
    """Endless training batches (:func:`draw_batch`) from the shards of ``folder``, read again every
    200 batches as it grows. Each worker process of a ``DataLoader`` draws from its own seed."""

    def __init__(self, folder: Path, batch: int, crop: int, seed: int, in_channels: int = 3) -> None:
        super().__init__()
        self.folder, self.batch, self.crop, self.seed, self.in_channels = Path(folder), batch, crop, seed, in_channels

    def __iter__(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        info = torch.utils.data.get_worker_info()
        rng = np.random.default_rng([self.seed, info.id if info is not None else 0])
        known: dict[str, Shard] = {}
        while True:
            if not load_shards(self.folder, known):
                print(f"waiting for shards in {self.folder}", file=sys.stderr, flush=True)
                while not load_shards(self.folder, known):
                    time.sleep(1.0)                    # a generator beside the training has not written one yet
            shards_grid_mm(known)
            for _ in range(200):
                x, y = draw_batch(list(known.values()), rng, self.batch, self.crop)
                yield (x if self.in_channels == 3 else x[:, 1:2]), y


def vary_contrast(x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Intensity changes the input function's percentile scaling does not undo, drawn per sample: a
    global scale (a bright coil-side rim or fat sets the percentile and darkens the rest), a gamma, a
    smooth multiplicative field across the crop (a head deep in the pelvis, far from the coil), and
    the neighbours' brightness apart from the slice's (interleaved acquisitions: odd and even slices
    differ by spin history and motion). The result stays in the input's 0..2 range."""
    x = x * rng.uniform(0.8, 1.25) ** np.sign(rng.standard_normal())
    if rng.random() < 0.4:
        x = x * np.exp(rng.uniform(-0.5, 0.5, 3) * np.array([1.0, 0.0, 1.0]))[:, None, None]
    if rng.random() < 0.3:
        x = x * rng.uniform(0.2, 0.8)
    if rng.random() < 0.4:
        x = 2.0 * (np.clip(x, 0.0, 2.0) / 2.0) ** np.exp(rng.uniform(-0.5, 0.5))
    if rng.random() < 0.5:
        h, w = x.shape[1:]
        field = ndimage.zoom(rng.standard_normal((3, 3)), (h / 3, w / 3), order=1, grid_mode=True, mode="nearest")
        x = x * np.exp(rng.uniform(0.2, 0.8) * field[:h, :w])
    return np.clip(x, 0.0, 2.0).astype(np.float32)
