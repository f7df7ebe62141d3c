"""Training of the brain localiser on synthetic shards (:mod:`model_export.localiser.dataset`).

Each step draws a batch of slices (most of them crossing the brain), rebuilds their 2.5D channels
exactly as the service does (:func:`~service.preprocess.localiser_inputs.with_neighbours`: a slice
between its neighbours, the ends repeated), crops a random ``crop`` x ``crop`` window (one that holds
the brain's centre where the slice has brain), flips and turns it, and minimises binary cross-entropy
plus soft Dice against the brain fraction of every pixel. The budget is a number of steps (the
reproducible one: the same seed, steps, settings and shards give the same weights) or minutes of
wall clock; the learning rate follows a cosine over it, so a run of any length ends annealed. A
checkpoint is written every ``checkpoint_s`` seconds and at the end, with what made it (seed,
budget, steps done, the shards' identity, the commit; :mod:`model_export.localiser.record`), and
training resumes from it.

Example (the learning rate of a 4-step budget, step by step):
    >>> [round(lr_at(1.0, step, 4), 3) for step in range(4)]
    [1.0, 0.854, 0.5, 0.146]
"""

from __future__ import annotations

import json
import random
import time
import warnings
from collections import deque
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from model_export.device import fast_cuda
from model_export.localiser.batches import BatchStream, one_grid_mm
from model_export.localiser.distil import distillation_loss, mirrored_logits, pruned
from model_export.localiser.export import load_checkpoint
from model_export.localiser.net import LocaliserNet
from model_export.localiser.record import data_record, file_record, git_state, shard_manifest


def loss_fn(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy plus soft Dice (over the batch)."""
    p = torch.sigmoid(logits)
    dice = 1 - (2 * (p * target).sum() + 1) / (p.sum() + target.sum() + 1)
    return F.binary_cross_entropy_with_logits(logits, target) + dice


def _budget(minutes: float | None, steps: int | None) -> tuple[float | None, int | None]:
    if (minutes is None) == (steps is None):
        raise ValueError("give one budget: steps (reproducible) or minutes (wall clock)")
    if (steps is not None and steps < 0) or (minutes is not None and minutes < 0):
        raise ValueError(f"a budget is not negative: steps {steps}, minutes {minutes}")
    return minutes, steps


def lr_at(lr: float, done: float, budget: float) -> float:
    """The learning rate after ``done`` of a ``budget`` (steps or seconds): a cosine from ``lr`` to 0."""
    return float(lr * 0.5 * (1 + np.cos(np.pi * min(done / budget, 1.0)))) if budget > 0 else 0.0


def seed_everything(seed: int) -> None:
    """Seed torch, numpy's global generator and Python's :mod:`random` (the batches have their own
    generator, :class:`BatchStream`'s)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def _resumed_network(out: Path, config: dict, in_channels: int, width: int, depth: int) -> tuple[int, int, int]:
    """The network a resumed run goes on with: the checkpoint's own (its ``in_channels``, ``width``
    and ``depth``), with a warning where the options given name another (a run's network cannot
    change shape halfway; ``--init`` starts a new run from a checkpoint of another width).

    Example:
        >>> _resumed_network(Path("w8.pt"), {"in_channels": 3, "width": 8, "depth": 4}, 3, 8, 4)
        (3, 8, 4)
    """
    saved = (int(config["in_channels"]), int(config["width"]), int(config["depth"]))
    if saved != (in_channels, width, depth):
        warnings.warn(f"{out} resumes its own network (channels {saved[0]}, width {saved[1]}, depth {saved[2]}), "
                      f"not channels {in_channels}, width {width}, depth {depth}: to start another network "
                      "from it, give a new --out and --init it", stacklevel=3)
    return saved


def network_shape(init: Path | None, width: int | None = None, depth: int | None = None) -> tuple[int, int]:
    """The width and depth of a new run: those asked, else ``init``'s (a run from a checkpoint keeps its
    depth and takes its width or a narrower one: its strongest channels), else 8 and 4.

    Raises:
        ValueError: ``init`` is no localiser checkpoint (not there, a pose network's), or the shape
            asked is not one it can start.
    """
    if init is None:
        return width or 8, depth or 4
    try:
        config = torch.load(init, map_location="cpu", weights_only=False)["config"]
        start = {k: int(config[k]) for k in ("in_channels", "width", "depth")}
    except Exception as bad:  # noqa: BLE001 - no file, a pose network's checkpoint, no checkpoint at all
        raise ValueError(f"--init {init}: not a localiser checkpoint ({type(bad).__name__}; a pose network's? "
                         "`svrnet-train train --init` takes those)") from None
    width, depth = width or start["width"], depth or start["depth"]
    if width > start["width"] or depth != start["depth"]:
        raise ValueError(f"--init {init} is a network of width {start['width']} and depth {start['depth']}: a new "
                         "run from it keeps its depth and takes its width or a narrower one")
    return width, depth


def train(data: Path, out: Path, minutes: float | None = None, *, steps: int | None = None, width: int = 8,
          depth: int = 4, batch: int = 16, crop: int = 128, lr: float = 2e-3, seed: int = 0,
          checkpoint_s: float = 120.0, threads: int = 2, log: Path | None = None, in_channels: int = 3,
          init: Path | None = None, teacher: Path | None = None, teacher_weight: float = 0.7,
          freeze_norm: bool = False, device: str = "cpu", loaders: int = 0) -> Path:
    """Train until the checkpoint has done ``steps`` steps, or for ``minutes`` more of wall clock
    (resuming ``out`` if it exists); returns the checkpoint path.

    Only the step budget is reproducible: the learning rate follows a cosine over the steps, and a
    run of the same seed, steps, settings and shards, uninterrupted, on the same device kind and
    threads, gives the same weights. A wall-clock budget anneals over the time instead, so its
    weights depend on the machine's speed. A resumed run draws its batches from ``seed`` plus the
    steps done, so it is not the uninterrupted run bit for bit (the checkpoint lists its runs).

    ``in_channels`` 3 is the 2.5D network (a slice and its neighbours), 1 the 2D one (the slice alone).
    ``init``: a checkpoint whose weights start a new run (a fresh optimiser and learning-rate schedule;
    fine-tuning on new data), used only when ``out`` does not exist yet; a checkpoint of another width
    starts the network from its strongest channels (:func:`~model_export.localiser.distil.pruned`).
    ``teacher``: a checkpoint whose mirrored-pass logits the network learns, ``teacher_weight`` of the
    loss (:func:`~model_export.localiser.distil.distillation_loss`); the rest is the true mask's.
    ``freeze_norm``: the batch-norm layers normalise with the running statistics they start with and
    keep them (their scales and shifts still learn), so the network trains as it runs in the service;
    in training mode a fine-tune normalises each crop by its own batch and moves the statistics the
    exported network uses.

    ``device``: where the network steps (``cuda`` on a GPU host); ``loaders``: worker processes that
    draw the batches (:class:`BatchStream`), for a host whose network step outruns one core's drawing.

    The checkpoint records the network grid its shards were made on (``grid_mm``; shards of two grids
    are refused), which :func:`~model_export.localiser.export.export_onnx` writes into the model file,
    and under ``training`` this run's settings, seed and budget, the steps done, the shard folder's
    identity and its shards' generator settings (:func:`~model_export.localiser.record.data_record`
    of the shards in the folder when it was written), the code's commit
    (:func:`~model_export.localiser.record.git_state`) and every run that made it (``runs``).

    Raises:
        ValueError: neither or both budgets given, or shards of two grids.
        FileNotFoundError: ``data`` is not a folder.
    """
    minutes, steps = _budget(minutes, steps)
    if not Path(data).is_dir():
        raise FileNotFoundError(f"data: {data} is not a folder of shards (`svrnet-train localiser data --out`)")
    torch.set_num_threads(threads)
    fast_cuda(device)
    seed_everything(seed)
    out = Path(out)
    state = torch.load(out, map_location="cpu", weights_only=False) if out.exists() else None   # our own
    if state is not None:
        in_channels, width, depth = _resumed_network(out, state["config"], in_channels, width, depth)
    net = LocaliserNet(in_channels=in_channels, width=width, depth=depth)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    step, spent, recorded, runs, started = 0, 0.0, None, [], None
    if init is not None and state is None:
        started = file_record(init)
        net.load_state_dict(pruned(load_checkpoint(init), width).state_dict())     # the identity at its own width
    teacher_net = load_checkpoint(teacher).to(device) if teacher is not None else None
    if state is not None:
        net.load_state_dict(state["model"])
        opt.load_state_dict(state["optimiser"])
        step, spent, recorded = state["step"], state.get("spent_s", 0.0), state.get("grid_mm")
        before = state.get("training", {})
        runs, started = before.get("runs", [{"from_step": 0, "to_step": step, "recorded": False}]), before.get("init")
    net.to(device)
    for values in opt.state.values():                  # a resumed optimiser's moments beside the weights
        values.update({k: v.to(device) for k, v in values.items() if torch.is_tensor(v) and k != "step"})
    budget = spent + (minutes or 0.0) * 60.0
    start, last_ckpt, first_step = time.perf_counter() - spent, time.perf_counter(), step
    losses: deque[torch.Tensor] = deque(maxlen=200)         # on the device: no wait for the GPU each step
    stream = BatchStream(data, batch, crop, seed + step, in_channels)
    batches = iter(stream if loaders == 0 else torch.utils.data.DataLoader(
        stream, batch_size=None, num_workers=loaders, pin_memory=device != "cpu", persistent_workers=True))

    manifest: dict[str, dict] = {}
    settings = {"seed": seed, "steps": steps, "minutes": minutes, "lr": lr, "batch": batch, "crop": crop,
                "teacher_weight": teacher_weight if teacher else None, "freeze_norm": freeze_norm,
                "device": device, "loaders": loaders, "threads": threads,
                "init": started,
                "teacher": file_record(teacher) if teacher is not None else None, "commit": git_state()}

    def save() -> None:
        shard_manifest(data, manifest)
        grid_mm = one_grid_mm([*(m["grid_mm"] for m in manifest.values()), recorded])
        run = {**settings, "from_step": first_step, "to_step": step, "data": data_record(data, manifest)}
        this = {**{k: v for k, v in run.items() if k != "data"}, "manifest_sha256": run["data"]["manifest_sha256"]}
        torch.save({"model": {k: v.cpu() for k, v in net.state_dict().items()}, "optimiser": opt.state_dict(),
                    "config": net.config, "step": step, "spent_s": time.perf_counter() - start,
                    "shards": len(manifest), "grid_mm": grid_mm, "training": {**run, "runs": [*runs, this]}}, out)

    def progress() -> None:
        if log is not None and losses:
            with open(log, "a") as f:
                f.write(json.dumps({"step": step, "elapsed_s": round(time.perf_counter() - start),
                                    "loss": float(torch.stack(tuple(losses)).mean()), "lr": opt.param_groups[0]["lr"]}) + "\n")

    net.train()
    if freeze_norm:
        for module in net.modules():
            if isinstance(module, torch.nn.BatchNorm2d):
                module.eval()
    while (step < steps) if steps is not None else ((elapsed := time.perf_counter() - start) < budget):
        for g in opt.param_groups:
            g["lr"] = lr_at(lr, step, steps) if steps is not None else lr_at(lr, elapsed, budget)
        x, y = (torch.as_tensor(t).to(device, non_blocking=True) for t in next(batches))
        if teacher_net is None:
            loss = loss_fn(net(x), y)
        else:
            loss = distillation_loss(net(x), mirrored_logits(teacher_net, x), y, teacher_weight, loss_fn)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.detach())
        step += 1
        if time.perf_counter() - last_ckpt > checkpoint_s:
            save()
            last_ckpt = time.perf_counter()
            progress()
    if step > first_step or not runs:                  # a finished budget leaves its checkpoint as it is
        save()
        progress()
    return out


def average_weights(base: Path, tuned: Path, out: Path, weight: float = 0.5) -> Path:
    """A checkpoint whose weights are ``weight`` of ``tuned``'s and the rest ``base``'s (weight-space
    ensembling of a fine-tuned network with the one it started from, as WiSE-FT does: the average
    keeps what the fine-tuning added and what it forgot, at one network's cost). ``tuned`` must have
    been fine-tuned from ``base`` (``train --init``); its training state is kept for resuming."""
    a = torch.load(base, map_location="cpu", weights_only=False)
    b = torch.load(tuned, map_location="cpu", weights_only=False)
    if a["config"] != b["config"]:
        raise ValueError(f"the two networks differ: {a['config']} and {b['config']}")
    mixed = {k: (weight * v.float() + (1 - weight) * a["model"][k].float()).to(v.dtype) if v.is_floating_point() else v
             for k, v in b["model"].items()}
    torch.save({**b, "model": mixed, "averaged": {"base": Path(base).name, "tuned": Path(tuned).name,
                                                  "weight": weight}}, out)
    return Path(out)



def main(argv: list[str] | None = None) -> Path:
    """``python -m model_export.localiser.train``: :func:`train` without typer, for a bare GPU host;
    the options are those of ``svrnet-train localiser train`` (``--channels`` its ``in_channels``)
    and :func:`train`'s keywords.

    Example:
        python -m model_export.localiser.train --data SHARDS --out $OUT/w6.pt --width 6 \\
            --init service/localisers/default/checkpoint.pt --teacher service/localisers/default/checkpoint.pt \\
            --lr 1e-3 --batch 64 --device cuda --loaders 2 --steps 6000
    """
    import argparse

    ap = argparse.ArgumentParser(prog="python -m model_export.localiser.train", description=main.__doc__)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    budget = ap.add_mutually_exclusive_group(required=True)
    budget.add_argument("--steps", type=int, help="train until the checkpoint has done this many steps (reproducible)")
    budget.add_argument("--minutes", type=float, help="train this many more minutes of wall clock (not reproducible)")
    for name, kind in (("width", int), ("depth", int), ("batch", int), ("crop", int), ("lr", float), ("seed", int),
                       ("threads", int), ("teacher-weight", float), ("loaders", int), ("checkpoint-s", float)):
        ap.add_argument(f"--{name}", type=kind)
    ap.add_argument("--channels", dest="in_channels", type=int, choices=(1, 3))
    ap.add_argument("--init", type=Path)
    ap.add_argument("--teacher", type=Path)
    ap.add_argument("--freeze-norm", action="store_true")
    ap.add_argument("--device", default="cpu")
    args = vars(ap.parse_args(argv))
    try:
        args["width"], args["depth"] = network_shape(args["init"], args["width"], args["depth"])
    except ValueError as bad:
        ap.error(str(bad))
    keywords = {k: v for k, v in args.items() if v is not None and k not in ("data", "out", "minutes")}
    return train(args["data"], args["out"], args["minutes"], log=Path(f"{args['out']}.log"), **keywords)


if __name__ == "__main__":              # run as the module itself, so its worker processes can find its functions
    from model_export.localiser.train import main as module_main

    module_main()
