"""Training: simulated slices streamed from a worker process, Adam with step decay, checkpoints.

The worker keeps a pool of clean acquisitions (the expensive 3D sampling) and re-corrupts and
re-preprocesses each of them several times (``reuse``) with fresh draws, so that the two CPU cores
are shared between simulation and the network without starving either.
"""

from __future__ import annotations

import csv
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset

from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes, split
from model_export.model import SVRNet, multi_loss
from model_export.simulate import Acquisition, SimulationConfig, SliceBatch, SliceSimulator
from service.geometry import anchors, encodings, se3


@dataclass
class TrainConfig:
    """Everything that defines a training run (saved in every checkpoint)."""

    backbone: str = "compact"
    width: float = 1.0
    label_type: str = "anchor"
    sampling: str = "random"
    steps: int = 20000
    batch: int = 64
    lr: float = 1e-4
    lr_milestones: tuple[float, ...] = (0.6, 0.85)
    lr_gamma: float = 0.2
    dropout: float = 0.5
    hidden: int = 128
    spatial_grid: int = 3
    grid_channels: int = 32
    loss_weights: tuple[float, ...] | None = None
    seed: int = 0
    val_every: int = 500
    val_per_volume: int = 100
    reuse: int = 6
    pool: int = 24
    threads: int = 1
    workers: int = 2
    train_volumes: list[str] | None = None
    val_volumes: list[str] | None = None
    simulation: dict = field(default_factory=dict)
    init_from: dict | None = None


class SliceStream(IterableDataset):
    """Endless batches from a :class:`SliceSimulator` with a pool of reusable acquisitions."""

    def __init__(self, names: list[str], root: Path, sim: SimulationConfig, label_type: str, batch: int,
                 reuse: int, pool: int, seed: int) -> None:
        self.names, self.root, self.sim, self.label_type, self.batch = names, root, sim, label_type, batch
        self.reuse, self.pool, self.seed = reuse, pool, seed

    def __iter__(self):  # noqa: ANN204 - generator
        torch.set_num_threads(1)
        info = torch.utils.data.get_worker_info()
        rng = np.random.default_rng(self.seed + (info.id if info else 0) * 7919)
        simulator = SliceSimulator(load_volumes(self.names, self.root), self.sim)
        per_group = 16
        groups = max(1, self.batch // per_group)

        def fresh():
            i = int(rng.integers(len(simulator.volumes)))
            c = simulator.config
            poses = simulator.sample_poses(simulator.volumes[i], per_group, rng)
            acq, thick, k = (float(rng.uniform(*c.acq_pixel_mm)), float(rng.uniform(*c.thickness_mm)),
                             float(rng.uniform(*c.brain_scale)))
            img, mask = simulator.acquire(i, poses, acq, thick, k)
            return Acquisition(img, mask, poses, acq, thick, k, simulator.volumes[i].name)

        pool = [fresh() for _ in range(self.pool)]
        refresh = max(1, round(groups / self.reuse))
        while True:
            picks = rng.choice(len(pool), size=groups, replace=False)
            parts = [simulator.finish(pool[j], rng) for j in picks]
            x = np.concatenate([p.inputs for p in parts])
            y = np.concatenate([encodings.encode(self.label_type, p.poses) for p in parts])
            yield torch.from_numpy(x[:, None]), torch.from_numpy(y.astype(np.float32))
            for j in rng.choice(len(pool), size=refresh, replace=False):
                pool[j] = fresh()


def validation_set(names: list[str], root: Path, per_volume: int, seed: int = 12345,
                   config: SimulationConfig | None = None) -> SliceBatch:
    """Fixed validation slices (3 mm thick, noisy) from whole held-out volumes."""
    sim = SliceSimulator(load_volumes(names, root), config or SimulationConfig.validation())
    rng = np.random.default_rng(seed)
    parts = [sim.simulate(i, per_volume, rng) for i in range(len(sim.volumes))]
    return SliceBatch(np.concatenate([p.inputs for p in parts]), np.concatenate([p.poses for p in parts]),
                      sum((p.volume for p in parts), []), np.concatenate([p.thickness_mm for p in parts]))


def label_sample(cfg: TrainConfig, root: Path, sim: SimulationConfig, n_per_volume: int = 200) -> np.ndarray:
    """Labels of random training poses (no rendering), for the output normalisation."""
    rng = np.random.default_rng(cfg.seed)
    simulator = SliceSimulator(load_volumes(cfg.train_volumes, root), sim)
    poses = np.concatenate([simulator.sample_poses(v, n_per_volume, rng) for v in simulator.volumes])
    return encodings.encode(cfg.label_type, poses)


@torch.no_grad()
def predict_poses(model: SVRNet, inputs: np.ndarray, batch: int = 256) -> np.ndarray:
    """Deterministic (eval-mode) poses ``[B, 4, 4]`` of network inputs ``[B, L, L]``."""
    model.eval()
    out = [model(torch.from_numpy(inputs[i:i + batch, None])).double().numpy() for i in range(0, len(inputs), batch)]
    return encodings.decode(model.label_type, np.concatenate(out))


def pose_errors(pred: np.ndarray, true: np.ndarray) -> dict[str, np.ndarray]:
    """Per-slice mean anchor-point Euclidean distance (mm) and geodesic distance."""
    ed = np.linalg.norm((anchors.encode(pred) - anchors.encode(true)).reshape(-1, 3, 3), axis=-1).mean(-1)
    return {"ed_mm": ed, "gd": se3.geodesic_distance(pred, true)}


def train(cfg: TrainConfig, out_dir: Path, root: Path = DEFAULT_ATLAS_ROOT, resume: Path | None = None,
          progress: bool = True, init: Path | None = None) -> Path:
    """Train, logging to ``out_dir/log.csv``; returns the path of the best checkpoint.

    Args:
        cfg: the run's configuration.
        out_dir: run folder (checkpoints, ``log.csv``, ``loss.png``, ``summary.json``).
        root: the atlas folder.
        resume: continue a run exactly (weights, optimiser, learning-rate schedule, step).
        progress: show a progress bar.
        init: start from this checkpoint's weights (and label normalisation) with a fresh optimiser
            and schedule of ``cfg.steps`` -- a second training stage. Samples seen and training time
            carry over, so the figures of the final checkpoint are the totals.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    train_names, val_names = split(root)
    cfg.train_volumes = cfg.train_volumes or train_names
    cfg.val_volumes = cfg.val_volumes or val_names
    sim = SimulationConfig(sampling=cfg.sampling, **cfg.simulation)
    model = SVRNet(cfg.backbone, cfg.width, cfg.label_type, sim.size, cfg.hidden, cfg.dropout, cfg.spatial_grid,
                   cfg.grid_channels)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    milestones = [int(m * cfg.steps) for m in cfg.lr_milestones]
    sched = torch.optim.lr_scheduler.MultiStepLR(opt, milestones, cfg.lr_gamma)
    val = validation_set(cfg.val_volumes, root, cfg.val_per_volume,
                         config=SimulationConfig.validation(size=sim.size, pixel_mm=sim.pixel_mm))
    step, best, seen, elapsed = 0, float("inf"), 0, 0.0
    if resume is not None:
        ck = torch.load(resume, map_location="cpu", weights_only=False)
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        sched.load_state_dict(ck["scheduler"])
        step, best, seen, elapsed = ck["step"], ck.get("best_ed_mm", best), ck.get("samples_seen", 0), ck.get("train_seconds", 0.0)
    elif init is not None:
        ck = torch.load(init, map_location="cpu", weights_only=False)
        if {**ck["model_config"], "dropout": model.config["dropout"]} != model.config:
            raise ValueError(f"--init {init}: its network {ck['model_config']} differs from {model.config}")
        model.load_state_dict(ck["model"])
        seen, elapsed = ck.get("samples_seen", 0), ck.get("train_seconds", 0.0)
        cfg.init_from = {"checkpoint": str(init), "steps": ck["step"], "samples_seen": seen,
                         "train_seconds": elapsed, "val_ed_mm": ck.get("val_ed_mm", float("nan"))}
    else:
        model.set_label_normalisation(torch.from_numpy(label_sample(cfg, root, sim)).float())

    stream = SliceStream(cfg.train_volumes, root, sim, cfg.label_type, cfg.batch, cfg.reuse, cfg.pool, cfg.seed + step)
    loader = iter(DataLoader(stream, batch_size=None, num_workers=cfg.workers, prefetch_factor=4, persistent_workers=True))
    log_path = out_dir / "log.csv"
    new_log = not log_path.exists() or resume is None
    log = open(log_path, "w" if new_log else "a", newline="")
    writer = csv.writer(log)
    branches = [n for n, _ in encodings.get(cfg.label_type).branches]
    if new_log:
        writer.writerow(["step", "samples", "seconds", "lr", "loss", *branches, "val_ed_mm", "val_ed_median_mm", "val_gd"])

    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn
    bar = Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                   TextColumn("{task.fields[info]}"), TimeRemainingColumn(), disable=not progress)
    best_path = out_dir / "best.pt"
    t0 = time.perf_counter() - elapsed
    with bar:
        task = bar.add_task("training", total=cfg.steps, completed=step, info="")
        running = None
        while step < cfg.steps:
            model.train()
            x, y = next(loader)
            target = (y - model.label_mean) / model.label_scale
            loss, parts = multi_loss(model.normalised(x), target, cfg.label_type, cfg.loss_weights)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            step += 1
            seen += len(x)
            running = float(loss.detach()) if running is None else 0.98 * running + 0.02 * float(loss.detach())
            row = None
            if step % cfg.val_every == 0 or step == cfg.steps:
                err = pose_errors(predict_poses(model, val.inputs), val.poses)
                ed, gd = float(err["ed_mm"].mean()), float(err["gd"].mean())
                row = [ed, float(np.median(err["ed_mm"])), gd]
                state = dict(model=model.state_dict(), optimizer=opt.state_dict(), scheduler=sched.state_dict(),
                             step=step, samples_seen=seen, train_seconds=time.perf_counter() - t0,
                             config=asdict(cfg), model_config=model.config, simulation=asdict(sim),
                             best_ed_mm=min(best, ed), val_ed_mm=ed)
                torch.save(state, out_dir / "last.pt")
                if ed < best:
                    best = ed
                    torch.save(state, best_path)
                bar.update(task, info=f"loss {running:.3f} val E.D. {ed:.2f} mm (best {best:.2f})")
            if step % 50 == 0 or row is not None:
                writer.writerow([step, seen, round(time.perf_counter() - t0, 1), sched.get_last_lr()[0],
                                 round(running, 5), *[round(parts[b], 5) for b in branches], *(row or ["", "", ""])])
                log.flush()
            bar.update(task, completed=step)
    log.close()
    plot_log(log_path, out_dir / "loss.png")
    (out_dir / "summary.json").write_text(json.dumps({"best_val_ed_mm": best, "steps": step, "samples_seen": seen,
                                                      "train_seconds": time.perf_counter() - t0}, indent=2))
    return best_path


def plot_log(log_path: Path, png: Path) -> None:
    """Loss and validation E.D. curves from a training log."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(csv.DictReader(open(log_path)))
    if not rows:
        return
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
    ax[0].plot([int(r["samples"]) for r in rows], [float(r["loss"]) for r in rows])
    ax[0].set(xlabel="samples", ylabel="multi-loss (normalised)", yscale="log", title="training loss")
    val = [r for r in rows if r["val_ed_mm"]]
    ax[1].plot([int(r["samples"]) for r in val], [float(r["val_ed_mm"]) for r in val], "o-")
    ax[1].set(xlabel="samples", ylabel="mm", title="validation mean anchor E.D.")
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
