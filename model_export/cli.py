"""``svrnet-train``: train, export, calibrate and evaluate SVRnet models.

Examples:
    svrnet-train train --steps 20000 --out runs/default
    svrnet-train export runs/default/best.pt service/models/default/model.onnx --threshold 25
    svrnet-train calibrate runs/default/best.pt
    svrnet-train evaluate service/models/default/model.onnx --report model_export/reports/default.md
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer

from model_export.atlas import DEFAULT_ATLAS_ROOT

app = typer.Typer(add_completion=False, help=__doc__, no_args_is_help=True)

Root = Annotated[Path, typer.Option(help="folder holding crl_sta/ and spina_bifida_cc0/")]


@app.command()
def train(
    out: Annotated[Path, typer.Option(help="run folder: checkpoints, log.csv, loss.png")] = Path("runs/default"),
    backbone: str = "compact",
    width: float = 1.0,
    label_type: Annotated[str, typer.Option(help="anchor, grid, euler or quaternion")] = "anchor",
    loss: Annotated[str, typer.Option(help="l2, or mirror-aware min / invariant (point labels)")] = "l2",
    sampling: Annotated[str, typer.Option(help="random, euler or fibonacci")] = "random",
    steps: int = 20000,
    batch: int = 64,
    lr: Annotated[float, typer.Option(help="Adam learning rate (step decay x0.2 at 60 % and 85 %)")] = 1e-4,
    constant_lr: Annotated[bool, typer.Option(help="no step decay")] = False,
    dropout: float = 0.5,
    val_every: int = 500,
    val_per_volume: int = 100,
    threads: int = 1,
    workers: Annotated[int, typer.Option(help="simulation worker processes")] = 2,
    reuse: Annotated[int, typer.Option(help="corruptions of each clean acquisition in the bank")] = 6,
    device: Annotated[str, typer.Option(help="cpu, cuda or auto")] = "cpu",
    max_minutes: Annotated[Optional[float], typer.Option(help="stop at a checkpoint after this wall time")] = None,
    plane_x_mm: Annotated[float, typer.Option(help="atlas symmetry plane x0 of the twin")] = 0.0,
    seed: int = 0,
    resume: Annotated[Optional[Path], typer.Option(help="checkpoint to continue from")] = None,
    init: Annotated[Optional[Path], typer.Option(help="checkpoint whose weights start a new stage "
                                                      "(fresh optimiser and schedule)")] = None,
    root: Root = DEFAULT_ATLAS_ROOT,
) -> None:
    """Train a model on simulated slices of the atlas volumes."""
    from model_export.train import TrainConfig, train as run

    cfg = TrainConfig(backbone=backbone, width=width, label_type=label_type, sampling=sampling, steps=steps,
                      batch=batch, lr=lr, dropout=dropout, val_every=val_every, threads=threads, seed=seed, loss=loss,
                      val_per_volume=val_per_volume, workers=workers, reuse=reuse, device=device,
                      max_minutes=max_minutes, plane_x_mm=plane_x_mm,
                      lr_milestones=() if constant_lr else TrainConfig.lr_milestones)
    best = run(cfg, out, root, resume, init=init)
    typer.echo(f"best checkpoint: {best}")


@app.command()
def pack(
    out: Annotated[Path, typer.Option(help="packed folder (one .npz per volume + packed.json)")] = Path("data/packed"),
    root: Root = DEFAULT_ATLAS_ROOT,
) -> None:
    """Pack the atlas volumes as .npz (numpy only: no SimpleITK needed where they are read)."""
    from model_export.atlas import pack as run

    path = run(out, root)
    size = sum(f.stat().st_size for f in path.iterdir())
    typer.echo(f"wrote {path} ({size / 1e6:.1f} MB)")


@app.command()
def export(
    checkpoint: Path,
    output: Path,
    name: str = "default",
    version: str = "0.1.0",
    threshold: Annotated[Optional[float], typer.Option(help="variance threshold (default: calibrate now)")] = None,
    root: Root = DEFAULT_ATLAS_ROOT,
) -> None:
    """Export a checkpoint to ONNX (MC dropout kept stochastic) with its metadata."""
    from model_export.calibrate import calibrate as run_calibration
    from model_export.export import count_random_nodes
    from model_export.packaging import export_checkpoint

    if threshold is None:
        threshold = run_calibration(checkpoint, root)["threshold"]
    path = export_checkpoint(checkpoint, output, name=name, version=version, variance_threshold=threshold)
    typer.echo(f"wrote {path} ({count_random_nodes(path)} random nodes, variance threshold {threshold:.3g})")


@app.command()
def calibrate(checkpoint: Path, root: Root = DEFAULT_ATLAS_ROOT, mc_samples: int = 100) -> None:
    """Choose the variance threshold on the validation volumes; print AUROC and the chosen value."""
    from model_export.calibrate import calibrate as run

    result = run(checkpoint, root, mc_samples=mc_samples)
    typer.echo(json.dumps({k: v for k, v in result.items() if not isinstance(v, list)}, indent=2))


@app.command()
def evaluate(
    model: Path,
    report: Annotated[Path, typer.Option(help="markdown report; figures beside it")] = Path("model_export/reports/default.md"),
    root: Root = DEFAULT_ATLAS_ROOT,
    per_volume: int = 100,
    mc_samples: int = 100,
) -> None:
    """The paper's metrics on the validation volumes, written as a markdown report."""
    from model_export.evaluate import evaluate as run

    summary = run(model, report, root, per_volume=per_volume, mc_samples=mc_samples)
    typer.echo(json.dumps(summary, indent=2))


@app.command()
def compare(
    out: Annotated[Path, typer.Option(help="folder for the runs and table.json")] = Path("runs/compare"),
    steps: int = 300,
    batch: int = 32,
    width: float = 0.25,
    root: Root = DEFAULT_ATLAS_ROOT,
) -> None:
    """Equal-budget training of the paper's six backbones (Table II at small width)."""
    from model_export.compare import compare as run, markdown

    typer.echo(markdown(run(out, steps=steps, batch=batch, width=width, root=root)))


@app.command()
def ship(
    checkpoint: Path,
    out: Annotated[Path, typer.Option(help="model folder the service reads")] = Path("service/models/default"),
    name: str = "default",
    version: str = "1.0.0",
    comparison: Annotated[Optional[Path], typer.Option(help="table.json of `compare`")] = None,
    report: Path = Path("model_export/reports/default.md"),
    root: Root = DEFAULT_ATLAS_ROOT,
) -> None:
    """Calibrate, export, evaluate and write the model card: the folder the service loads."""
    import shutil

    from model_export.calibrate import calibrate as run_calibration
    from model_export.card import load_json, write_card
    from model_export.evaluate import evaluate as run_evaluation
    from model_export.packaging import export_checkpoint, load_checkpoint
    from service.inference.model_file import load_model

    out.mkdir(parents=True, exist_ok=True)
    cal = run_calibration(checkpoint, root)
    typer.echo(f"calibrated variance threshold {cal['threshold']:.4g} (AUROC {cal['auroc']:.3f})")
    onnx_path = export_checkpoint(checkpoint, out / "model.onnx", name=name, version=version,
                                  variance_threshold=cal["threshold"])
    shutil.copyfile(checkpoint, out / "checkpoint.pt")
    evaluation = run_evaluation(onnx_path, report, root)
    from model_export.train import prior_history, totals

    _, ck = load_checkpoint(checkpoint)
    summary = {"train_seconds": ck["train_seconds"], "samples_seen": ck["samples_seen"], "steps": ck["step"],
               "totals": totals(prior_history(ck)), "history": prior_history(ck),
               "train_volumes_text": f"{len(ck['config']['train_volumes'])} atlas volumes: "
                                     + ", ".join(ck["config"]["train_volumes"])}
    info = load_model(onnx_path).info.metadata
    write_card(out / "card.md", info=info, train_summary=summary, train_config=ck["config"], calibration=cal,
               evaluation=evaluation, comparison=load_json(comparison) if comparison else None,
               report_path=str(report), onnx_bytes=onnx_path.stat().st_size)
    (out / "calibration.json").write_text(json.dumps(cal))
    typer.echo(json.dumps(evaluation, indent=2))


if __name__ == "__main__":
    app()
