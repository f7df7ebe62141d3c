"""``svrnet-train localiser``: generate synthetic stacks, train, ship (export, evaluate, card).

Examples:
    svrnet-train localiser data --out runs/localiser/train --count 600
    svrnet-train localiser data --out runs/localiser/heldout --count 40 --style heldout --seed 1000000 --keep-stack
    svrnet-train localiser train --data runs/localiser/train --out runs/localiser/localiser.pt --steps 12000
    svrnet-train localiser ship runs/localiser/localiser.pt --heldout runs/localiser/heldout --out runs/localiser/next \\
        --version 1.3.0
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer

from model_export.atlas import DEFAULT_ATLAS_ROOT
from model_export.cli_options import Root
from model_export.localiser import GRID_MM

app = typer.Typer(add_completion=False, help=__doc__, no_args_is_help=True,
                  rich_markup_mode=None)     # click's plain help: every option's help and default whole
CHECKPOINT_GRID = ("the network grid (mm); default: the one the checkpoint's shards were made on, which it records "
                   f"({GRID_MM} for a checkpoint that does not); another is refused")


@app.command()
def data(
    out: Annotated[Path, typer.Option(help="shard folder")],
    count: int = 600,
    style: Annotated[str, typer.Option(help="train (training surroundings) or heldout (the validation set's)")] = "train",
    seed: Annotated[int, typer.Option(help="first seed; shards are named by seed and never rewritten")] = 0,
    keep_stack: Annotated[bool, typer.Option(help="keep each stack and mask (for evaluation)")] = False,
    workers: int = 2,
    grid_mm: float = GRID_MM,
    root: Root = DEFAULT_ATLAS_ROOT,
    shading_share: Annotated[float, typer.Option(help="share of stacks with a dark region over the head "
                                                      "(3 T shading, signal voids)")] = 0.0,
    faint_skull_share: Annotated[float, typer.Option(help="share of heads whose skull is thin and nearly as bright "
                                                          "as the fluid (a young fetus's)")] = 0.0,
    motion: Annotated[Optional[str], typer.Option(help="the heads move as at this level of the pose benchmarks (mild, "
                                                        "moderate, jumps, independent) over an interleaved acquisition; "
                                                        "default: the generator's own drift")] = None,
) -> None:
    """Synthetic whole-uterus stacks: training volumes for ``train``, validation volumes for ``heldout``."""
    from model_export.atlas import split, training_volumes
    from model_export.localiser.dataset import generate
    from model_export.localiser.scenes import MOTIONS

    if motion is not None and motion not in MOTIONS:
        raise typer.BadParameter(f"{motion!r} is not one of {', '.join(MOTIONS)}", param_hint="--motion")

    names = generate(out, training_volumes(root) if style == "train" else split(root)[1], count, style, grid_mm, seed, workers,
                     keep_stack, root, shading_share, faint_skull_share, motion)
    typer.echo(f"{len(names)} shards in {out}")


@app.command()
def train(
    data: Annotated[Path, typer.Option(help="shard folder of `data` (read again as it grows)")],
    out: Annotated[Path, typer.Option(help="checkpoint (resumed when it exists)")],
    steps: Annotated[Optional[int], typer.Option(help="train until the checkpoint has done this many steps; the "
                                                      "learning rate anneals over them (reproducible: the same seed, "
                                                      "steps, settings and shards give the same weights)")] = None,
    minutes: Annotated[Optional[float], typer.Option(help="instead of --steps: this many more minutes of wall clock "
                                                          "(not reproducible: the weights depend on the machine's "
                                                          "speed)")] = None,
    width: Annotated[Optional[int], typer.Option(help="channels of the finest level [default: --init's, else 8]")] = None,
    depth: Annotated[Optional[int], typer.Option(help="levels [default: --init's, else 4]")] = None,
    threads: int = 2,
    seed: int = 0,
    channels: Annotated[int, typer.Option(help="3: 2.5D (a slice between its neighbours); 1: 2D")] = 3,
    init: Annotated[Optional[Path], typer.Option(help="start from this localiser checkpoint's weights, fresh optimiser")] = None,
    lr: float = 2e-3,
    teacher: Annotated[Optional[Path], typer.Option(help="distil: learn this checkpoint's mirrored-pass logits")] = None,
    teacher_weight: Annotated[float, typer.Option(help="the teacher's share of the loss (the rest: the true mask)")] = 0.7,
    freeze_norm: Annotated[bool, typer.Option(help="batch norm at its running statistics (a fine-tune trains as the "
                                                   "service runs it)")] = False,
    batch: Annotated[int, typer.Option(help="crops per step")] = 16,
    device: Annotated[str, typer.Option(help="cpu or cuda (on a GPU host; `python -m model_export.localiser.train` "
                                             "there needs no typer)")] = "cpu",
    loaders: Annotated[int, typer.Option(help="processes that draw the batches from the shards (0: the training "
                                              "process; `data --workers` are those that generate scenes); each "
                                              "holds the shards it has read in memory")] = 0,
) -> None:
    """Train (or continue training) the localiser for ``--steps`` (or ``--minutes``); progress in
    ``<out>.log`` (at each checkpoint and the last step). The checkpoint records the seed, budget, steps
    done, the shards' identity and the commit. With ``--init`` of another width the network starts from
    that one's strongest channels."""
    from model_export.localiser.train import network_shape, train as run

    if (steps is None) == (minutes is None):
        raise typer.BadParameter("give one budget: --steps (reproducible) or --minutes", param_hint="--steps")
    if not data.is_dir():
        raise typer.BadParameter(f"{data} is not a folder of shards (`svrnet-train localiser data --out`)",
                                 param_hint="--data")
    for path, hint in ((init, "--init"), (teacher, "--teacher")):
        if path is not None:
            localiser_checkpoint(path, hint)
    try:
        width, depth = network_shape(init, width, depth)
    except ValueError as bad:
        raise typer.BadParameter(str(bad)) from None
    before = localiser_checkpoint(out, "--out")["step"] if out.exists() else 0
    run(data, out, minutes, steps=steps, width=width, depth=depth, threads=threads, seed=seed, log=Path(f"{out}.log"),
        in_channels=channels, init=init, lr=lr, teacher=teacher, teacher_weight=teacher_weight, freeze_norm=freeze_norm,
        batch=batch, device=device, loaders=loaders)
    after = localiser_checkpoint(out, "--out")["step"]
    typer.echo(f"nothing to do: {out} has done {after} steps (--steps counts them all)" if after == before
               else f"{out}: steps {before} to {after}")


@app.command()
def average(
    base: Annotated[Path, typer.Argument(help="the checkpoint the fine-tuning started from")],
    tuned: Annotated[Path, typer.Argument(help="the fine-tuned checkpoint (`train --init BASE`)")],
    out: Annotated[Path, typer.Option(help="the averaged checkpoint")],
    weight: Annotated[float, typer.Option(help="share of the fine-tuned weights")] = 0.5,
) -> None:
    """Average a fine-tuned network's weights with those it started from (weight-space ensembling)."""
    from model_export.localiser.train import average_weights

    localiser_checkpoint(base, "BASE")
    localiser_checkpoint(tuned, "TUNED")
    try:
        typer.echo(str(average_weights(base, tuned, out, weight)))
    except ValueError as differ:                          # two networks of other widths or depths
        raise typer.BadParameter(str(differ), param_hint="TUNED") from None


CHECKPOINT_COPY_MB = 64.0
"""``ship`` copies a checkpoint up to this size beside the model (the shipped width-8 one: 4 MB);
a larger one is recorded by its sha256 alone."""


@app.command()
def ship(
    checkpoint: Path,
    heldout: Annotated[Path, typer.Option(help="shard folder of `data --style heldout --keep-stack`")],
    out: Annotated[Path, typer.Option(help="the new model's folder (the service loads every folder of "
                                           "SVRNET_LOCALISERS_DIR; its default, the one stacks without masks go "
                                           "to, is the folder named default)")],
    version: Annotated[str, typer.Option(help="the version the model file and the card carry")],
    force: Annotated[bool, typer.Option(help="replace a folder that already holds files")] = False,
    grid_mm: Annotated[Optional[float], typer.Option(help=CHECKPOINT_GRID)] = None,
    pose_stacks: Annotated[int, typer.Option(help="held-out stacks whose poses are compared without/with masks")] = 8,
    ablation: Annotated[Optional[Path], typer.Option(help="JSON of `compare`: architectures measured alike")] = None,
    pose_scenes: Annotated[int, typer.Option(help="whole-uterus scenes of known slice poses: pose accuracy vs the truth")] = 10,
    mirrored_pass: Annotated[str, typer.Option(help="run: the service adds the mirror-image pass; learnt: a "
                                               "network distilled from it (`train --teacher`) runs once")] = "run",
) -> None:
    """Export to ONNX, measure (held-out set, real scans, poses without masks) and write the card, into
    ``--out`` with the checkpoint (or its sha256 where it is over 64 MB). The card is written from the
    checkpoint's record and the measurements; small budgets make it a quick look, which it says. The
    folder is built beside ``--out`` and takes its place only when whole: a server never finds a
    localiser without its card."""
    import os
    import shutil

    from model_export.localiser.card import write_card
    from model_export.localiser.evaluate import measure
    from model_export.localiser.export import export_onnx
    from model_export.localiser.record import data_record, file_record, git_state, shard_manifest
    from model_export.shipping import ship_folder
    from service.preprocess.localise import Localiser

    if mirrored_pass not in ("run", "learnt"):
        raise typer.BadParameter("run or learnt", param_hint="--mirrored-pass")
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not force:
        raise typer.BadParameter(f"{out} is not an empty folder; give a new one, or --force to write into it",
                                 param_hint="--out")
    for path, hint in ((checkpoint, "CHECKPOINT"), (heldout, "--heldout"), (ablation, "--ablation")):
        if path is not None and path.resolve().is_relative_to(out.resolve()):
            raise typer.BadParameter(f"{path} lies inside {out}, which ship replaces: move it out first",
                                     param_hint=hint)
    state = localiser_checkpoint(checkpoint)
    check_heldout(heldout)
    record = file_record(checkpoint)
    copied = record["bytes"] <= CHECKPOINT_COPY_MB * 2**20

    def build(staging: Path, _report: Path, _shown: Path) -> dict:
        try:
            onnx_path = export_onnx(checkpoint, staging / "model.onnx", grid_mm=grid_mm, version=version,
                                    extra={"mirrored_pass": mirrored_pass, "checkpoint_sha256": record["sha256"],
                                           "steps": state.get("step", 0)})
        except ValueError as e:
            raise typer.BadParameter(str(e), param_hint="--grid-mm") from None
        if copied:
            shutil.copyfile(checkpoint, staging / "checkpoint.pt")
        figures = measure(Localiser.load(onnx_path), heldout, pose_stacks, pose_scenes=pose_scenes)
        figures["architectures"] = json.loads(ablation.read_text()) if ablation else []
        figures["shipped"] = {"version": version, "checkpoint": {**record, "copied": copied},
                              "training": state.get("training"), "step": state.get("step", 0),
                              "shards": state.get("shards", 0), "config": state["config"],
                              "heldout": {k: v for k, v in data_record(heldout, shard_manifest(heldout, {})).items()
                                          if k != "names"},
                              "commit": git_state(), "machine": f"{os.cpu_count()} CPU cores"}
        (staging / "evaluation.json").write_text(json.dumps(figures, indent=1))
        write_card(staging / "card.md", onnx_path, figures)
        return figures

    figures = ship_folder(out, None, build)
    typer.echo(json.dumps(figures["summary"], indent=1))
    if not copied:
        typer.echo(f"{checkpoint} is {record['bytes'] / 2**20:.0f} MB: not copied; the card records its sha256")


def localiser_checkpoint(path: Path, hint: str = "CHECKPOINT") -> dict:
    """The localiser checkpoint ``path`` as ``train`` wrote it; :class:`typer.BadParameter` naming
    ``hint`` and what the file is instead (none, a pose network's, not a checkpoint)."""
    import torch

    if not path.is_file():
        raise typer.BadParameter(f"{path}: no such file", param_hint=hint)
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)             # our own checkpoint
    except (OSError, RuntimeError, EOFError, ValueError) as e:
        raise typer.BadParameter(f"{path} is no checkpoint ({type(e).__name__})", param_hint=hint) from None
    if not isinstance(state, dict) or "in_channels" not in (state.get("config") or {}):
        raise typer.BadParameter(f"{path} is not a localiser checkpoint (a pose network's? `svrnet-train ship` "
                                 "and `train` take those)", param_hint=hint)
    return state


def check_heldout(folder: Path) -> None:
    """:class:`typer.BadParameter` unless ``folder`` holds shards that keep their stacks (``data --style
    heldout --keep-stack``), before anything is exported or measured."""
    import numpy as np

    shards = sorted(Path(folder).glob("*.npz"))
    if not shards:
        raise typer.BadParameter(f"{folder} holds no shards (.npz): make them with `svrnet-train localiser data "
                                 "--style heldout --keep-stack`", param_hint="--heldout")
    with np.load(shards[0]) as z:
        if "stack" not in z.files:
            raise typer.BadParameter(f"{folder}'s shards keep no stack: make them with `--keep-stack`",
                                     param_hint="--heldout")


@app.command()
def compare(
    checkpoints: Annotated[list[Path], typer.Argument(help="checkpoints trained alike (same data, seed, minutes)")],
    heldout: Annotated[Path, typer.Option(help="shard folder of `data --style heldout --keep-stack`")],
    out: Annotated[Path, typer.Option(help="JSON rows for `ship --ablation`")],
    grid_mm: Annotated[Optional[float], typer.Option(help=CHECKPOINT_GRID)] = None,
    real_scans: Annotated[Optional[list[Path]], typer.Option(
        help="folders of real scans (SCAN/NAME.nii.gz beside SCAN/NAME_brain_mask.nii.gz); repeat; "
             "default real_scans/ of ../shared/data or of SVRNET_SHARED_DATA (tools/fetch_real_scan.py fetches one more)")] = None,
    mirrored: Annotated[Optional[bool], typer.Option(
        "--mirrored/--single-pass", help="with or without the mirror-image pass (default: both, one row each)")] = None,
) -> None:
    """Dice of each checkpoint on the held-out set and the real scans: the architecture chosen by measurement."""
    import tempfile

    import numpy as np

    from model_export.localiser.evaluate import REAL_SCANS, heldout_dice, latency_ms, real_scan_rows
    from model_export.localiser.export import export_onnx, load_checkpoint
    from service.preprocess.localise import Localiser

    rows = []
    for ckpt in checkpoints:
        try:
            onnx_path = export_onnx(ckpt, Path(tempfile.mkdtemp()) / "model.onnx", grid_mm=grid_mm, version=ckpt.stem)
        except ValueError as e:
            raise typer.BadParameter(str(e), param_hint="--grid-mm") from None
        config = load_checkpoint(ckpt).config
        loc = Localiser.load(onnx_path)
        for passes in ([True, False] if mirrored is None else [mirrored]):
            loc.mirrored = passes
            held = [r["dice"] for r in heldout_dice(loc, heldout)]
            stacks = [r for root in (real_scans or [REAL_SCANS]) for r in real_scan_rows(loc, root)]
            real = [r["dice"] for r in stacks if r["dice"] is not None]
            rows.append({"checkpoint": ckpt.name, "inputs": "2.5D" if config["in_channels"] == 3 else "2D", **config,
                         "mirrored": passes,
                         "heldout_median_dice": float(np.median(held)), "heldout_min_dice": float(np.min(held)),
                         "heldout_mean_dice": float(np.mean(held)),
                         "real_median_dice": float(np.median(real)) if real else None,
                         "real_min_dice": float(np.min(real)) if real else None,
                         "real_dice": {r["stack"]: round(r["dice"], 3) for r in stacks if r["dice"] is not None},
                         "real_ml": {r["stack"]: round(r["ml"]) for r in stacks if r["dice"] is None},
                         "ms": latency_ms(loc)})
            typer.echo(json.dumps(rows[-1]))
    out.write_text(json.dumps(rows, indent=1))
