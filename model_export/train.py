"""Training: simulated slices streamed from worker processes, Adam with step decay, checkpoints.

* Data: :class:`~model_export.stream.SliceStream` workers (CPU) simulate slices exactly as the
  service preprocesses them; the network trains on ``device`` (``cpu``, ``cuda`` or ``auto``).
* Loss: point labels (``anchor``, ``grid``) train with :func:`~model_export.losses.point_loss`
  (``l2``, or mirror-aware ``min`` / ``invariant``); other labels with the paper's multi-loss.
* Validation: deterministic pass on fixed held-out slices; the error against the truth (E.D.) and
  the twin-min E.D. (to whichever of truth and twin is nearer); the best checkpoint is chosen on
  the twin-min E.D. (a single slice cannot tell the twins apart).
* Training compounds: every checkpoint carries ``history``, one segment per run (hardware, device,
  samples, seconds, loss, label), and ``samples_seen`` / ``train_seconds`` are the totals over all
  of them. ``resume`` continues a run (its weights, optimiser, schedule and step; its slices drawn
  afresh, so it ends near, not at, the uninterrupted run); ``init`` starts a new stage from a checkpoint's
  weights (the whole network, or only the trunk when the label type changes). ``max_minutes``
  stops at a checkpoint when a wall-clock budget is spent (a later ``resume`` goes on).
"""

from __future__ import annotations

import argparse
import csv
import json
import time
import warnings
from collections import Counter
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from model_export.atlas import DEFAULT_ATLAS_ROOT, VALIDATION_VOLUMES, split
from model_export.device import resolve_device
from model_export.losses import check_label_type, point_loss
from model_export.model import SVRNet, multi_loss
from model_export.simulate import SimulationConfig
from model_export.stream import SLICES_PER_ACQUISITION, SliceStream, label_sample, validation_set
from model_export.train_config import TrainConfig, check_root, default_loss, parse_fields, stage_config
from model_export.training_record import git_commit, hardware, plot_log, prior_history, totals
from service.geometry import anchors, encodings, se3
from service.geometry.twin import POINT_LABELS, twin

__all__ = ["train", "stream_seed", "predict_poses", "pose_errors", "validation_set"]


def stream_seed(seed: int, samples_seen: int) -> int:
    """The training stream's seed for a run that starts (or resumes) after ``samples_seen`` samples.

    Every stage and every resume draws new slices: a stage started from a checkpoint must not replay
    the stream an earlier stage already trained on (their samples would repeat).

    Example:
        >>> stream_seed(0, 0) == stream_seed(0, 0), stream_seed(0, 0) == stream_seed(0, 64)
        (True, False)
    """
    return int(np.random.SeedSequence([seed, samples_seen]).generate_state(1)[0])


@torch.no_grad()
def predict_poses(model: SVRNet, inputs: np.ndarray, batch: int = 256) -> np.ndarray:
    """Deterministic (eval-mode) poses ``[B, 4, 4]`` of network inputs ``[B, L, L]`` (on the model's device)."""
    model.eval()
    device = next(model.parameters()).device
    out = [model(torch.from_numpy(inputs[i:i + batch, None]).to(device)).double().cpu().numpy()
           for i in range(0, len(inputs), batch)]
    return encodings.decode(model.label_type, np.concatenate(out))


def pose_errors(pred: np.ndarray, true: np.ndarray, plane_x_mm: float = 0.0) -> dict[str, np.ndarray]:
    """Per slice: the mean anchor-point E.D. (mm) and the G.D., to the truth and to the nearer twin.

    Returns ``ed_mm`` (against the truth), ``ed_twin_mm`` (twin-min: against whichever of the truth
    and its twin is nearer), ``on_twin`` (the twin is strictly nearer), ``gd`` (to the truth) and
    ``gd_twin`` (to that nearer one).

    Example (a pose on the twin of the truth: 0 twin-min, far from the truth):
        >>> true = se3.exp(np.array([[0.2, 0.1, 0.3, 20.0, 5.0, 0.0]]))
        >>> err = pose_errors(twin(true), true)
        >>> bool(err["ed_mm"][0] > 30), float(err["ed_twin_mm"][0]), float(err["gd_twin"][0])
        (True, 0.0, 0.0)
    """
    twins = twin(true, plane_x_mm)
    e_true, e_twin = anchors.ed(pred, true), anchors.ed(pred, twins)
    on_twin = e_twin < e_true
    nearer = np.where(on_twin[..., None, None], twins, true)
    return {"ed_mm": e_true, "ed_twin_mm": np.minimum(e_true, e_twin), "on_twin": on_twin,
            "gd": se3.geodesic_distance(pred, true), "gd_twin": se3.geodesic_distance(pred, nearer)}


def _load_init(model: SVRNet, ck: dict, path: Path) -> bool:
    """Load ``ck``'s weights into ``model``: all of them, or the trunk only for another label type.

    Returns True when the whole network (and its label normalisation) was loaded.
    """
    mine, theirs = model.config, {"spatial_grid": 0, **ck["model_config"]}
    if {**theirs, "dropout": mine["dropout"]} == mine:
        model.load_state_dict(ck["model"])
        return True
    if {**theirs, "dropout": mine["dropout"], "label_type": mine["label_type"]} != mine:
        raise ValueError(f"--init {path}: its network {ck['model_config']} differs from {mine}")
    trunk = {k: v for k, v in ck["model"].items() if k.startswith(("trunk.", "grid.", "head.shared."))}
    model.load_state_dict(trunk, strict=False)
    return False


def _loss(model: SVRNet, x: torch.Tensor, y: torch.Tensor, cfg: TrainConfig) -> torch.Tensor:
    if cfg.label_type in POINT_LABELS:
        return point_loss(model(x), y, model.label_mean, model.label_scale, cfg.loss, cfg.plane_x_mm).mean()
    target = (y - model.label_mean) / model.label_scale
    return multi_loss(model.normalised(x), target, cfg.label_type, cfg.loss_weights)[0]


def train(cfg: TrainConfig, out_dir: Path, root: Path = DEFAULT_ATLAS_ROOT, resume: Path | None = None,
          progress: bool = True, init: Path | None = None) -> Path:
    """Train, logging to ``out_dir/log.csv``; returns the path of the best checkpoint.

    Args:
        cfg: the run's configuration.
        out_dir: run folder (checkpoints, ``log.csv``, ``loss.png``, ``summary.json``).
        root: the atlas folder or a packed folder (:func:`model_export.atlas.pack`).
        resume: continue a run (weights, optimiser, step, history; the learning-rate schedule of
            ``cfg``, whose steps may be new; its slices drawn afresh from a new stream seed).
        progress: show a progress bar.
        init: start from this checkpoint's weights (and label normalisation) with a fresh optimiser
            and schedule of ``cfg.steps`` -- a new training stage. Its history carries over, so the
            figures of the final checkpoint are the totals.
    """
    cfg.loss = cfg.loss or default_loss(cfg.label_type)
    check_label_type(cfg.label_type, cfg.loss)
    if cfg.batch % SLICES_PER_ACQUISITION or min(cfg.batch, cfg.steps, cfg.val_every, cfg.val_per_volume, cfg.reuse) < 1:
        raise ValueError(f"batch {cfg.batch} (a multiple of {SLICES_PER_ACQUISITION}: whole acquisitions), steps "
                         f"{cfg.steps}, val_every {cfg.val_every}, val_per_volume {cfg.val_per_volume}, reuse "
                         f"{cfg.reuse}: each at least 1")
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    device = resolve_device(cfg.device)
    train_names, val_names = split(root, cfg.val_volumes or VALIDATION_VOLUMES)
    cfg.train_volumes = cfg.train_volumes or train_names
    cfg.val_volumes = cfg.val_volumes or val_names
    if set(cfg.train_volumes) & set(cfg.val_volumes):
        raise ValueError(f"volumes both trained and validated on: {sorted(set(cfg.train_volumes) & set(cfg.val_volumes))}")
    sim = SimulationConfig(sampling=cfg.sampling, **cfg.simulation)
    model = SVRNet(cfg.backbone, cfg.width, cfg.label_type, sim.size, cfg.hidden, cfg.dropout, cfg.spatial_grid,
                   cfg.grid_channels)
    step, best, history = 0, float("inf"), []
    ck = None
    if resume is not None:
        ck = torch.load(resume, map_location="cpu", weights_only=False)
        model.load_state_dict(ck["model"])
        step, best = ck["step"], ck.get("best_ed_mm", best)
        history = prior_history(ck)
        cfg.init_from = ck["config"].get("init_from")
        if step >= cfg.steps:                          # its files stay as they are
            print(f"nothing to do: {resume} has done {step} of {cfg.steps} steps (--steps counts them all; a "
                  "resumed run goes on to it)")
            return out_dir / "best.pt"
    elif init is not None:
        prev = torch.load(init, map_location="cpu", weights_only=False)
        whole = _load_init(model, prev, init)
        if not whole:
            warnings.warn(f"--init {init}: its network has {prev['model_config'].get('label_type')} labels, this "
                          f"stage {cfg.label_type}: only the trunk is loaded and the head starts afresh", stacklevel=2)
            model.set_label_normalisation(torch.from_numpy(
                label_sample(cfg.train_volumes, cfg.label_type, root, sim, cfg.seed)).float())
        history = prior_history(prev)
        cfg.init_from = {"checkpoint": str(init), "steps": prev["step"], "samples_seen": prev.get("samples_seen", 0),
                         "train_seconds": prev.get("train_seconds", 0.0), "whole_network": whole,
                         "val_ed_mm": prev.get("val_ed_mm", float("nan"))}
    else:
        model.set_label_normalisation(torch.from_numpy(
            label_sample(cfg.train_volumes, cfg.label_type, root, sim, cfg.seed)).float())
    model.to(device)
    if cfg.channels_last:
        model.to(memory_format=torch.channels_last)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    milestones = [int(m * cfg.steps) for m in cfg.lr_milestones]
    sched = torch.optim.lr_scheduler.MultiStepLR(opt, milestones, cfg.lr_gamma)
    if resume is not None:
        opt.load_state_dict(ck["optimizer"])
        sched.load_state_dict(ck["scheduler"])
        # This run's schedule (its steps, milestones and lr may be new), from the step it resumes at.
        sched.milestones = Counter(milestones)
        decays = sum(1 for m in milestones if m <= sched.last_epoch)
        for group in opt.param_groups:
            group["initial_lr"], group["lr"] = cfg.lr, cfg.lr * cfg.lr_gamma ** decays
        sched.base_lrs = [cfg.lr] * len(opt.param_groups)
    # This run's own segment; a resumed run continues the segment of its checkpoint when the hardware matches.
    segment = {"hardware": hardware(device), "device": device.type, "samples": 0, "seconds": 0.0, "steps": 0,
               "label_type": cfg.label_type, "loss": cfg.loss, "run": str(out_dir),
               "config": {k: v for k, v in asdict(cfg).items() if k != "init_from"}}    # the stage's recipe
    if resume is not None and history and history[-1].get("run") == str(out_dir) \
            and history[-1]["hardware"] == segment["hardware"]:
        segment = {**history.pop(), "config": segment["config"]}            # as it goes on now (its steps)
    segment["commits"] = list(dict.fromkeys([*segment.get("commits", []), git_commit()]))    # the code of each start
    base = {"samples": segment["samples"], "seconds": segment["seconds"], "steps": segment["steps"]}
    val = validation_set(cfg.val_volumes, root, cfg.val_per_volume,
                         config=SimulationConfig.validation(size=sim.size, pixel_mm=sim.pixel_mm))

    seed = stream_seed(cfg.seed, totals(history)["samples"] + base["samples"])
    segment["stream_seeds"] = [*segment.get("stream_seeds", []), seed]
    stream = SliceStream(cfg.train_volumes, root, sim, cfg.label_type, cfg.batch, cfg.reuse, cfg.pool, seed,
                         cfg.scene_share, cfg.scene_reuse)
    loader = iter(DataLoader(stream, batch_size=None, num_workers=cfg.workers, prefetch_factor=4 if cfg.workers else None,
                             persistent_workers=cfg.workers > 0, pin_memory=device.type == "cuda"))
    log_path = out_dir / "log.csv"
    new_log = not log_path.exists() or resume is None
    log = open(log_path, "w" if new_log else "a", newline="")
    writer = csv.writer(log)
    if new_log:
        writer.writerow(["step", "samples", "seconds", "lr", "loss", "val_ed_mm", "val_ed_median_mm",
                         "val_twin_ed_mm", "val_twin_ed_median_mm", "val_twin_ed_p90_mm", "val_twin_under_10mm",
                         "val_gd"])

    bar = _progress_bar(progress)
    best_path = out_dir / "best.pt"
    t_start, run_steps = time.perf_counter(), 0
    deadline = t_start + 60.0 * cfg.max_minutes if cfg.max_minutes is not None else float("inf")
    with bar:
        task = bar.add_task("training", total=cfg.steps, completed=step, info="")
        running = None
        while step < cfg.steps:
            model.train()
            x, y = next(loader)
            x, y = x.to(device, non_blocking=True), y.to(device, non_blocking=True)
            if cfg.channels_last:
                x = x.contiguous(memory_format=torch.channels_last)
            loss = _loss(model, x, y, cfg)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            step += 1
            run_steps += 1
            value = loss.detach()                 # averaged on the device: no wait for the GPU each step
            running = value if running is None else 0.98 * running + 0.02 * value
            out_of_time = time.perf_counter() >= deadline
            segment.update(samples=base["samples"] + run_steps * cfg.batch, steps=base["steps"] + run_steps,
                           seconds=base["seconds"] + time.perf_counter() - t_start)
            row = None
            if step % cfg.val_every == 0 or step == cfg.steps or out_of_time:
                err = pose_errors(predict_poses(model, val.inputs), val.poses, cfg.plane_x_mm)
                ed, ed_twin = err["ed_mm"], err["ed_twin_mm"]
                score = float(ed_twin.mean())
                row = [float(ed.mean()), float(np.median(ed)), score, float(np.median(ed_twin)),
                       float(np.percentile(ed_twin, 90)), float((ed_twin < 10.0).mean()), float(err["gd"].mean())]
                full = history + [dict(segment)]
                tot = totals(full)
                state = dict(model={k: v.cpu() for k, v in model.state_dict().items()}, optimizer=opt.state_dict(),
                             scheduler=sched.state_dict(), step=step, samples_seen=tot["samples"],
                             train_seconds=tot["hours"] * 3600, history=full, config=asdict(cfg),
                             model_config=model.config, simulation=asdict(sim), best_ed_mm=min(best, score),
                             val_ed_mm=float(ed.mean()), val_twin_ed_mm=score)
                torch.save(state, out_dir / "last.pt")
                if score < best:
                    best = score
                    torch.save(state, best_path)
                bar.update(task, info=f"loss {float(running):.3f} val twin-min E.D. {score:.2f} mm (best {best:.2f})")
            if step % 50 == 0 or row is not None:
                writer.writerow([step, totals(history + [segment])["samples"], round(segment["seconds"], 1),
                                 sched.get_last_lr()[0], round(float(running), 5), *(row or [""] * 7)])
                log.flush()
            bar.update(task, completed=step)
            if out_of_time:
                break
    log.close()
    plot_log(log_path, out_dir / "loss.png")
    (out_dir / "summary.json").write_text(json.dumps({"best_val_twin_ed_mm": best, "steps": step,
                                                      "finished": step >= cfg.steps,
                                                      "totals": totals(history + [segment])}, indent=2))
    return best_path


def _progress_bar(progress: bool):  # noqa: ANN202 - rich's Progress, or a silent stand-in
    """A rich progress bar; a silent stand-in when rich is missing (a bare GPU host) or not wanted."""
    try:
        from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn
    except ImportError:
        progress = False
    if not progress:
        class Silent:
            def __enter__(self): return self                   # noqa: E704, ANN204
            def __exit__(self, *exc): return False             # noqa: E704, ANN204, ANN002
            def add_task(self, *a, **k): return 0              # noqa: E704, ANN202, ANN002, ANN003
            def update(self, *a, **k): pass                    # noqa: E704, ANN202, ANN002, ANN003
        return Silent()
    return Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                    TextColumn("{task.fields[info]}"), TimeRemainingColumn())


def main(argv: list[str] | None = None) -> Path:
    """``python -m model_export.train``: the same training with numpy, scipy and torch only (no typer).

    For a bare GPU host. Any :class:`TrainConfig` field is set as ``field=value`` (JSON values). With
    ``--resume`` the run's own configuration is the starting point, with ``--init`` the configuration
    of the stage that wrote the checkpoint (all but :data:`HOST_FIELDS`), so only changes need naming:
    a new stage keeps the network, its labels and its loss unless a field says otherwise.

    Example:
        python -m model_export.train --out $OUT/run --root data/packed --init service/models/default/checkpoint.pt \\
            device=auto workers=14 steps=9000 max_minutes=6.5 simulation='{"surroundings_share": 0.6}'
    """
    ap = argparse.ArgumentParser(prog="python -m model_export.train", description=main.__doc__)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--root", type=Path, default=DEFAULT_ATLAS_ROOT)
    ap.add_argument("--init", type=Path)
    ap.add_argument("--resume", type=Path)
    ap.add_argument("fields", nargs="*", help="TrainConfig overrides, field=value (JSON)")
    args = ap.parse_args(argv)
    if args.resume is not None and args.init is not None:
        ap.error("a run resumes (--resume) or starts a new stage (--init), not both")
    try:
        cfg = stage_config(parse_fields(ap, args.fields, TrainConfig), args.resume, args.init)
        check_root(args.root, cfg)
    except ValueError as bad:
        ap.error(str(bad))
    best = train(cfg, args.out, args.root, resume=args.resume, init=args.init, progress=False)
    print(json.loads((args.out / "summary.json").read_text()))
    return best


if __name__ == "__main__":
    main()
