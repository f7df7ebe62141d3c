"""A narrower pose trunk taught by the shipped network: the same head, the same answers, less arithmetic.

The trunk is the network's cost at inference: it runs once per slice and test-time view, the MC
passes repeat only the small head. :func:`distil` trains narrower trunks (``students``) to give the
teacher's features, the 288 numbers its head reads, on the slices the service feeds it:

* **The head is the teacher's, frozen**, and so is its label normalisation: a student whose features
  match reproduces the teacher's MC spread, so the calibrations made on the teacher's poses start
  from the right place (``ship`` measures them again).
* **Loss**: the squared feature error, each feature scaled by the teacher's spread of it (at least a
  tenth of the median spread: a feature that hardly varies is not blown up), plus the
  mean distance (mm / 10) between the grid points the frozen head gives from the student's features
  and from the teacher's: features that matter for the pose count for more.
* **Every batch in all eight test-time views** (the four turns of the square, with and without a
  flip): the service asks the network about every view, and eight samples of a simulated slice cost
  the teacher and the students one GPU pass each.
* **Several students at once**: simulation (CPU workers) bounds the run, the students' steps are
  nearly free beside it, so they share one stream of slices. ``sliced`` students start from the
  teacher's first channels of every layer, ``fresh`` ones from random weights, and a student given
  as its checkpoint goes on from it (its history carried over).

The learning rate warms up, then follows a cosine over the wall-clock budget, so a run of any length
ends annealed. Each student's checkpoint is written at every validation (``w<width>-<start>.pt``, ``next`` for a
student that went on from a checkpoint; the format of
:mod:`model_export.train`, history carried over), and ``ship`` takes it as it takes a trained one.
Needs numpy, scipy and torch only (a bare GPU host):

    python -m model_export.distil --out $OUT --root data/packed \\
        --teacher service/models/default/checkpoint.pt --students 0.5:sliced,0.75:sliced \\
        device=cuda workers=14 minutes=8
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from model_export.atlas import DEFAULT_ATLAS_ROOT, validation_volumes
from model_export.model import SVRNet
from model_export.simulate import SimulationConfig
from model_export.stream import SliceStream, validation_set
from model_export.device import resolve_device
from model_export.train import pose_errors, predict_poses, stream_seed
from model_export.train_config import parse_fields
from model_export.training_record import git_commit, hardware, prior_history, totals

__all__ = ["DistilConfig", "distil", "narrowed", "student_config", "student_of"]


@dataclass
class DistilConfig:
    """One distillation run (saved in every student's checkpoint as ``distil``)."""

    students: list[str] = field(default_factory=lambda: ["0.5:sliced"])
    lr: float = 2e-3
    warmup_steps: int = 200
    minutes: float = 8.0
    max_steps: int | None = None
    output_weight: float = 0.1
    views: int = 8
    batch: int = 64
    reuse: int = 6
    pool: int = 24
    workers: int = 2
    threads: int = 1
    device: str = "cpu"
    seed: int = 17
    val_every_s: float = 60.0
    val_per_volume: int = 60
    simulation: dict = field(default_factory=lambda: {"surroundings_share": 0.3, "mask_wobble_share": 0.3,
                                                      "mask_wobble_px": [0.0, 4.0]})


def narrowed(teacher_state: dict[str, torch.Tensor], student: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The teacher's weights cut to the student's shapes: the first channels of every layer.

    Example:
        >>> a, b = torch.nn.Conv2d(4, 8, 3), torch.nn.Conv2d(2, 4, 3)
        >>> s = narrowed(a.state_dict(), b)
        >>> s["weight"].shape, bool(torch.equal(s["weight"], a.weight[:4, :2]))
        (torch.Size([4, 2, 3, 3]), True)
    """
    out = {}
    for key, mine in student.state_dict().items():
        theirs = teacher_state[key]
        out[key] = theirs[tuple(slice(0, n) for n in mine.shape)].clone() if mine.dim() else theirs.clone()
    return out


def student_of(teacher: SVRNet, width: float, start: str | dict) -> SVRNet:
    """A network of ``width`` with the teacher's head and label normalisation (frozen); its trunk
    ``sliced`` from the teacher's, ``fresh``, or an earlier run's student (its checkpoint dict: the
    run goes on from it)."""
    student = SVRNet(**{**teacher.config, "width": width})
    if isinstance(start, dict):
        student.load_state_dict(start["model"])
    elif start == "sliced":
        student.load_state_dict(narrowed(teacher.state_dict(), student))
    elif start != "fresh":
        raise ValueError(f"student start {start!r}: 'sliced', 'fresh' or an earlier student's checkpoint (.pt)")
    student.head.load_state_dict(teacher.head.state_dict())
    student.label_mean.copy_(teacher.label_mean)
    student.label_scale.copy_(teacher.label_scale)
    for p in student.head.parameters():
        p.requires_grad_(False)
    return student


def student_config(teacher_config: dict, width: float, cfg: DistilConfig, teacher_path: Path, spec: str) -> dict:
    """A student checkpoint's ``config``: the teacher's network and volumes at ``width``, the
    simulation overrides the run used, and the run's own recipe under ``distil`` (what a model card
    states of its last stage).

    Example:
        >>> c = student_config({"width": 1.0, "simulation": {"tz_fraction": 0.5}}, 0.75, DistilConfig(), Path("t.pt"), "0.75")
        >>> c["width"], c["simulation"]["tz_fraction"], c["distil"]["teacher"]
        (0.75, 0.47, 't.pt')
    """
    simulation = {**teacher_config.get("simulation", {}), "tz_fraction": SimulationConfig.tz_fraction, **cfg.simulation}
    return {**teacher_config, "width": width, "simulation": simulation,
            "init_from": {"checkpoint": str(teacher_path), "distil": spec},
            "distil": {**asdict(cfg), "teacher": str(teacher_path)}}


def all_views(x: torch.Tensor, n: int) -> torch.Tensor:
    """``x [B, 1, L, L]`` in ``n`` test-time views (the first 4 turns, then the same flipped), stacked."""
    flips = [x, torch.flip(x, dims=(-1,))] if n > 4 else [x]
    return torch.cat([torch.rot90(f, k, dims=(-2, -1)) for f in flips for k in range(min(n, 4))])


def _head_points(model: SVRNet, features: torch.Tensor) -> torch.Tensor:
    """The frozen head's deterministic grid points ``[B, P, 3]`` (mm) from features."""
    out = model.head(features, lambda t: t) * model.label_scale + model.label_mean
    return out.reshape(len(out), -1, 3)


def _lr_factor(step: int, elapsed: float, budget: float, warmup: int) -> float:
    """Linear warm-up over ``warmup`` steps, then a cosine over the wall-clock budget.

    Example:
        >>> _lr_factor(0, 0.0, 10.0, 100), _lr_factor(500, 5.0, 10.0, 100), _lr_factor(900, 10.0, 10.0, 100)
        (0.01, 0.5, 0.0)
    """
    if step < warmup:
        return (step + 1) / warmup
    return 0.5 * (1.0 + math.cos(math.pi * min(1.0, elapsed / budget)))


def distil(cfg: DistilConfig, out_dir: Path, teacher_path: Path, root: Path = DEFAULT_ATLAS_ROOT) -> dict:
    """Train every student of ``cfg`` against the teacher checkpoint; returns the run's summary."""
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    device = resolve_device(cfg.device)
    if device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
        torch.backends.cudnn.benchmark = True
    ck = torch.load(teacher_path, map_location="cpu", weights_only=False)
    teacher = SVRNet.from_checkpoint(ck).to(device)
    names = {s: (float(s.partition(":")[0]), s.partition(":")[2] or "sliced") for s in cfg.students}
    configs = {s: student_config(ck["config"], w, cfg, teacher_path, s) for s, (w, _) in names.items()}
    shared = next(iter(configs.values()))                  # every student sees the same slices
    sim = SimulationConfig(sampling=shared.get("sampling", "random"), **shared["simulation"])   # as train() builds it
    earlier = {s: torch.load(start, map_location="cpu", weights_only=False)
               for s, (_, start) in names.items() if start.endswith(".pt")}
    students = {s: student_of(teacher, w, earlier.get(s, start)).to(device) for s, (w, start) in names.items()}
    histories = {s: prior_history(earlier.get(s, ck)) for s in names}
    opts = {s: torch.optim.Adam([p for p in m.parameters() if p.requires_grad], lr=cfg.lr) for s, m in students.items()}

    val_cfg = SimulationConfig.validation(size=sim.size, pixel_mm=sim.pixel_mm)
    val = validation_set(validation_volumes(ck), root, cfg.val_per_volume, config=val_cfg)
    teacher_val = predict_poses(teacher, val.inputs)
    plane = float(ck["config"].get("plane_x_mm", 0.0))
    seed = stream_seed(cfg.seed, max(totals(h)["samples"] for h in histories.values()))   # never a replay
    code = git_commit()                                    # the code this run is at (-dirty: with changes)
    stream = SliceStream(ck["config"]["train_volumes"], root, sim, teacher.label_type, cfg.batch, cfg.reuse, cfg.pool,
                         seed)
    loader = iter(DataLoader(stream, batch_size=None, num_workers=cfg.workers,
                             prefetch_factor=4 if cfg.workers else None, persistent_workers=cfg.workers > 0,
                             pin_memory=device.type == "cuda"))
    log = open(out_dir / "log.csv", "w")
    log.write("step,slices,seconds,lr," + ",".join(f"loss[{s}],ed[{s}],twin_ed[{s}],to_teacher[{s}]" for s in students) + "\n")
    teacher_err = pose_errors(teacher_val, val.poses, plane)
    summary: dict = {"teacher_val_ed_mm": float(teacher_err["ed_mm"].mean()),
                     "teacher_val_twin_ed_mm": float(teacher_err["ed_twin_mm"].mean()), "students": {}}
    scale, running = None, {s: None for s in students}
    budget, step, slices = 60.0 * cfg.minutes, 0, 0
    t0 = last_val = time.perf_counter()
    while True:
        x, _ = next(loader)
        x = all_views(x.to(device, non_blocking=True), cfg.views)
        with torch.no_grad():
            t_feat = teacher.features(x)
            t_pts = _head_points(teacher, t_feat)
            if scale is None:
                spread = t_feat.std(0)
                scale = spread.clamp_min(0.1 * float(spread.median()) + 1e-6)
        elapsed = time.perf_counter() - t0
        lr = cfg.lr * _lr_factor(step, elapsed, budget, cfg.warmup_steps)
        for s, m in students.items():
            m.train()
            m.head.eval()
            feat = m.features(x)
            loss = (((feat - t_feat) / scale) ** 2).mean() \
                + cfg.output_weight * torch.linalg.vector_norm(_head_points(m, feat) - t_pts, dim=-1).mean() / 10.0
            for g in opts[s].param_groups:
                g["lr"] = lr
            opts[s].zero_grad(set_to_none=True)
            loss.backward()
            opts[s].step()
            v = float(loss.detach())
            running[s] = v if running[s] is None else 0.98 * running[s] + 0.02 * v
        step += 1
        slices += cfg.batch
        done = elapsed >= budget or (cfg.max_steps is not None and step >= cfg.max_steps)
        if done or time.perf_counter() - last_val >= cfg.val_every_s:
            last_val = time.perf_counter()
            row = [str(step), str(slices), f"{last_val - t0:.1f}", f"{lr:.2e}"]
            for s, m in students.items():
                poses = predict_poses(m, val.inputs)
                errors = pose_errors(poses, val.poses, plane)
                ed, err = errors["ed_mm"], errors["ed_twin_mm"]
                to_teacher = pose_errors(poses, teacher_val, plane)["ed_mm"]
                segment = {"hardware": hardware(device), "device": device.type, "samples": slices, "views": cfg.views,
                           "seconds": last_val - t0, "steps": step, "label_type": teacher.label_type,
                           "loss": "distil", "run": str(out_dir), "stream_seeds": [seed], "commits": [code]}
                full = histories[s] + [segment]
                tot = totals(full)
                width, start = names[s]
                state = dict(model={k: v.cpu() for k, v in m.state_dict().items()}, step=step,
                             samples_seen=tot["samples"], train_seconds=tot["hours"] * 3600, history=full,
                             config=configs[s], model_config=m.config, simulation=asdict(sim),
                             val_ed_mm=float(ed.mean()), val_twin_ed_mm=float(err.mean()), best_ed_mm=float(err.mean()),
                             val_ed_to_teacher_mm=float(np.median(to_teacher)))
                torch.save(state, out_dir / f"w{width:g}-{'next' if s in earlier else start}.pt")
                summary["students"][s] = {"val_ed_mm": float(ed.mean()), "val_twin_ed_mm": float(err.mean()),
                                          "val_twin_ed_median_mm": float(np.median(err)),
                                          "to_teacher_median_mm": float(np.median(to_teacher)),
                                          "to_teacher_mean_mm": float(to_teacher.mean())}
                row += [f"{running[s]:.4f}", f"{ed.mean():.2f}", f"{err.mean():.2f}", f"{np.median(to_teacher):.2f}"]
            log.write(",".join(row) + "\n")
            log.flush()
            print(" ".join(row), flush=True)
        if done:
            break
    log.close()
    summary.update(steps=step, slices=slices, seconds=time.perf_counter() - t0, hardware=hardware(device))
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def main(argv: list[str] | None = None) -> dict:
    """``python -m model_export.distil``: fields of :class:`DistilConfig` as ``field=value`` (JSON)."""
    ap = argparse.ArgumentParser(prog="python -m model_export.distil", description=main.__doc__)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--root", type=Path, default=DEFAULT_ATLAS_ROOT)
    ap.add_argument("--teacher", type=Path, default=Path("service/models/default/checkpoint.pt"))
    ap.add_argument("--students", default="0.5:sliced", help="WIDTH:sliced|fresh|CKPT.pt, comma-separated")
    ap.add_argument("fields", nargs="*", help="DistilConfig overrides, field=value (JSON)")
    args = ap.parse_args(argv)
    values = {"students": args.students.split(","), **parse_fields(ap, args.fields, DistilConfig)}
    summary = distil(DistilConfig(**values), args.out, args.teacher, args.root)
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main()
