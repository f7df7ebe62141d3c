"""The data side of training: an endless stream of simulated slices, and the fixed validation slices.

:class:`SliceStream` runs in DataLoader worker processes, on the CPU, whatever device trains the
network (simulation and the service's numpy preprocessing stay off the accelerator; a GPU host has
the cores to run many workers). Each worker keeps a **bank** of clean thick-slice acquisitions (the
expensive 3D sampling, :meth:`SliceSimulator.acquire`) and re-corrupts and re-preprocesses each of
them ``reuse`` times with fresh draws (:meth:`SliceSimulator.finish`): bias, gamma, voids, noise
and the imperfect mask change every time, the pose does not. With ``scene_share`` a share of each
batch comes instead from generated whole-uterus scenes cut with the localiser's own masks
(:class:`~model_export.scene_slices.ScenePool`).

Example (needs the atlas, or a packed folder, as ``root``):
    >>> from model_export.simulate import SimulationConfig                     # doctest: +SKIP
    >>> s = SliceStream(["STA30"], root, SimulationConfig(), "anchor", 32, reuse=6, pool=8, seed=0)  # doctest: +SKIP
    >>> x, y = next(iter(s)); x.shape, y.shape                                  # doctest: +SKIP
    (torch.Size([32, 1, 96, 96]), torch.Size([32, 9]))
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.utils.data import IterableDataset

from model_export.atlas import load_volumes
from model_export.simulate import Acquisition, SimulationConfig, SliceBatch, SliceSimulator
from service.geometry import encodings

SLICES_PER_ACQUISITION = 16
"""Slices acquired together (one volume, one pixel size, thickness and brain scale)."""


class SliceStream(IterableDataset):
    """Endless batches ``(inputs [B, 1, L, L], labels [B, D])`` from a bank of reusable acquisitions.

    Args:
        names: training volumes.
        root: atlas folder or packed folder.
        sim: simulation ranges.
        label_type: the label encoding.
        batch: slices per batch (groups of :data:`SLICES_PER_ACQUISITION`).
        reuse: on average how many times each clean acquisition is re-corrupted before replacement.
        pool: acquisitions in the bank.
        seed: base seed (each worker adds its id).
        scene_share: share of each batch cut with the localiser's masks from generated scenes, in
            whole groups of :data:`SLICES_PER_ACQUISITION` (0.25 of 64: one group of 16).
        scene_reuse: how many times, on average, each scene slice is drawn.
    """

    def __init__(self, names: list[str], root: Path, sim: SimulationConfig, label_type: str, batch: int,
                 reuse: int, pool: int, seed: int, scene_share: float = 0.0, scene_reuse: float = 8.0) -> None:
        self.names, self.root, self.sim, self.label_type, self.batch = names, root, sim, label_type, batch
        self.reuse, self.pool, self.seed = reuse, pool, seed
        if not 0.0 <= scene_share <= 1.0:
            raise ValueError(f"scene_share {scene_share}: a share between 0 and 1")
        self.scene_share, self.scene_reuse = scene_share, scene_reuse

    def __iter__(self):  # noqa: ANN204 - generator
        torch.set_num_threads(1)
        info = torch.utils.data.get_worker_info()
        rng = np.random.default_rng(self.seed + (info.id if info else 0) * 7919)
        simulator = SliceSimulator(load_volumes(self.names, self.root), self.sim)
        groups = max(1, self.batch // SLICES_PER_ACQUISITION)
        scene_groups = min(groups, int(round(groups * self.scene_share)))
        scenes = scene_pool(simulator, rng, self.scene_reuse) if scene_groups else None
        simulated = groups - scene_groups
        pool = [fresh_acquisition(simulator, rng) for _ in range(max(self.pool, groups) if simulated else 0)]
        owed = 0.0                # fresh acquisitions owed: each is corrupted `reuse` times on average
        while True:
            picks = rng.choice(len(pool), size=simulated, replace=False)
            parts = [simulator.finish(pool[j], rng) for j in picks]
            if scenes is not None:
                inputs, poses = scenes.draw(scene_groups * SLICES_PER_ACQUISITION)
                parts.append(SliceBatch(inputs, poses))
            x = np.concatenate([p.inputs for p in parts])
            y = np.concatenate([encodings.encode(self.label_type, p.poses) for p in parts])
            yield torch.from_numpy(x[:, None]), torch.from_numpy(y.astype(np.float32))
            owed += simulated / self.reuse if simulated else 0.0
            refresh = min(int(owed), len(pool))
            owed -= refresh
            for j in rng.choice(len(pool), size=refresh, replace=False):
                pool[j] = fresh_acquisition(simulator, rng)


def scene_pool(simulator: SliceSimulator, rng: np.random.Generator, reuse: float):  # noqa: ANN201 - a ScenePool
    """A worker's :class:`~model_export.scene_slices.ScenePool` over the simulator's volumes, with the
    service's localiser on one thread (imported here: a stream without scenes needs no localiser)."""
    from model_export.scene_slices import LazyHeads, ScenePool
    from service.core.settings import DEFAULT_LOCALISERS_DIR
    from service.preprocess.localise import Localiser

    localiser = Localiser.load(DEFAULT_LOCALISERS_DIR / "default" / "model.onnx", threads=1)
    return ScenePool(LazyHeads(simulator.volumes), localiser, simulator.config.size, simulator.config.pixel_mm, rng,
                     reuse=reuse)


def fresh_acquisition(simulator: SliceSimulator, rng: np.random.Generator,
                      n: int = SLICES_PER_ACQUISITION) -> Acquisition:
    """Clean thick slices of a random volume with one random acquisition setting."""
    return simulator.acquisition(int(rng.integers(len(simulator.volumes))), n, rng)


def validation_set(names: list[str], root: Path, per_volume: int, seed: int = 12345,
                   config: SimulationConfig | None = None) -> SliceBatch:
    """Fixed validation slices (3 mm thick, noisy) from whole held-out volumes."""
    sim = SliceSimulator(load_volumes(names, root), config or SimulationConfig.validation())
    rng = np.random.default_rng(seed)
    parts = [sim.simulate(i, per_volume, rng) for i in range(len(sim.volumes))]
    return SliceBatch(np.concatenate([p.inputs for p in parts]), np.concatenate([p.poses for p in parts]),
                      sum((p.volume for p in parts), []), np.concatenate([p.thickness_mm for p in parts]))


def label_sample(names: list[str], label_type: str, root: Path, sim: SimulationConfig, seed: int,
                 n_per_volume: int = 200) -> np.ndarray:
    """Labels of random training poses (no rendering), for the output normalisation."""
    rng = np.random.default_rng(seed)
    simulator = SliceSimulator(load_volumes(names, root), sim)
    poses = np.concatenate([simulator.sample_poses(v, n_per_volume, rng) for v in simulator.volumes])
    return encodings.encode(label_type, poses)
