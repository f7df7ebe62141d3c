"""``svrnet-train``: train, export, calibrate and evaluate SVRnet models.

Examples:
    svrnet-train train --label-type grid --loss min --dropout 0.25 --steps 20000 --out runs/default
    svrnet-train export runs/default/best.pt runs/default/model.onnx   # threshold calibrated on export
    svrnet-train calibrate runs/default/best.pt
    svrnet-train calibrate-acceptance runs/default/model.onnx
    svrnet-train calibrate-noise runs/default/model.onnx
    svrnet-train calibrate-frame runs/default/model.onnx
    svrnet-train evaluate service/models/default/model.onnx --report model_export/reports/default.md
    svrnet-train quantise service/models/default/model.onnx /tmp/model-int8.onnx
    svrnet-train localiser --help
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer

from model_export.atlas import DEFAULT_ATLAS_ROOT
from model_export.calibration_cli import COMMANDS as CALIBRATION_COMMANDS
from model_export.cli_options import PoseCheckpoint, PoseModel, Root, ValidationRoot
from model_export.localiser.cli import app as localiser_app
from service.inference.views import SHIPPED_VIEWS

app = typer.Typer(add_completion=False, help=__doc__, no_args_is_help=True,
                  rich_markup_mode=None)     # click's plain help: every option's help and default whole
app.add_typer(localiser_app, name="localiser", help="the brain localiser: synthetic data, training, shipping")
for _name, _command in CALIBRATION_COMMANDS.items():
    app.command(_name)(_command)


@app.command()
def train(
    out: Annotated[Path, typer.Option(help="run folder: checkpoints, log.csv, loss.png")] = Path("runs/default"),
    backbone: Annotated[Optional[str], typer.Option()] = None,
    width: Annotated[Optional[float], typer.Option()] = None,
    label_type: Annotated[Optional[str], typer.Option(help="anchor, grid, euler or quaternion")] = None,
    loss: Annotated[Optional[str], typer.Option(help="l2, or mirror-aware min / invariant (point labels; default min for "
                                                         "them, l2 for the others)")] = None,
    sampling: Annotated[Optional[str], typer.Option(help="random, euler or fibonacci")] = None,
    steps: Annotated[Optional[int], typer.Option(min=1)] = None,
    batch: Annotated[Optional[int], typer.Option(min=16, help="slices a step, a multiple of 16")] = None,
    lr: Annotated[Optional[float], typer.Option(help="Adam learning rate (step decay x0.2 at 60 % and 85 %)")] = None,
    constant_lr: Annotated[Optional[bool], typer.Option(
        help="no step decay; --no-constant-lr the step decay again (after a stage at a constant rate)")] = None,
    dropout: Annotated[Optional[float], typer.Option()] = None,
    val_every: Annotated[Optional[int], typer.Option(min=1)] = None,
    val_per_volume: Annotated[Optional[int], typer.Option(min=1)] = None,
    threads: Annotated[Optional[int], typer.Option()] = None,
    workers: Annotated[Optional[int], typer.Option(help="simulation worker processes")] = None,
    reuse: Annotated[Optional[int], typer.Option(min=1, help="corruptions of each clean acquisition in the bank")] = None,
    device: Annotated[Optional[str], typer.Option(help="cpu, cuda or auto")] = None,
    max_minutes: Annotated[Optional[float], typer.Option(help="stop at a checkpoint after this wall time")] = None,
    plane_x_mm: Annotated[Optional[float], typer.Option(help="atlas symmetry plane x0 of the twin")] = None,
    seed: Annotated[Optional[int], typer.Option()] = None,
    simulation: Annotated[Optional[str], typer.Option(
        help='the simulation\'s settings as JSON, e.g. \'{"surroundings_share": 0.3}\' (model_export/simulate.py, '
             "SimulationConfig)")] = None,
    resume: Annotated[Optional[Path], typer.Option(help="checkpoint to continue from, with its run's settings "
                                                        "(options given override them)")] = None,
    init: Annotated[Optional[Path], typer.Option(help="checkpoint whose weights start a new stage (fresh optimiser "
                                                      "and schedule); the stage that wrote it gives every setting "
                                                      "not given but the host's")] = None,
    root: Root = DEFAULT_ATLAS_ROOT,
) -> None:
    """Train a model on simulated slices of the atlas volumes. An option not given takes the value of
    the run --resume continues, else of the stage --init starts from (not its host's device, workers,
    threads or time budget), else TrainConfig's (model_export/train_config.py)."""
    from model_export.stream import SLICES_PER_ACQUISITION
    from model_export.train import train as run
    from model_export.train_config import TrainConfig, check_root, stage_config

    given = {k: v for k, v in dict(
        backbone=backbone, width=width, label_type=label_type, sampling=sampling, steps=steps, batch=batch, lr=lr,
        dropout=dropout, val_every=val_every, threads=threads, seed=seed, loss=loss, val_per_volume=val_per_volume,
        workers=workers, reuse=reuse, device=device, max_minutes=max_minutes, plane_x_mm=plane_x_mm).items()
        if v is not None}
    if constant_lr is not None:
        given["lr_milestones"] = () if constant_lr else TrainConfig.lr_milestones
    if simulation is not None:
        try:
            given["simulation"] = json.loads(simulation)
        except json.JSONDecodeError as bad:
            raise typer.BadParameter(f"not JSON: {bad}", param_hint="--simulation") from None
    if resume is not None and init is not None:
        raise typer.BadParameter("a run resumes or starts a new stage, not both", param_hint="--init")
    try:
        cfg = stage_config(given, resume, init)
        check_root(root, cfg)
    except ValueError as bad:
        raise typer.BadParameter(str(bad)) from None
    if cfg.batch % SLICES_PER_ACQUISITION:
        raise typer.BadParameter(f"{cfg.batch}: slices come in groups of {SLICES_PER_ACQUISITION}", param_hint="--batch")
    best = run(cfg, out, root, resume, init=init)
    typer.echo(f"best checkpoint: {best}")


@app.command()
def pack(
    out: Annotated[Path, typer.Option(help="packed folder (one .npz per volume + packed.json)")] = Path("data/packed"),
    root: Root = DEFAULT_ATLAS_ROOT,
    training_only: Annotated[bool, typer.Option(help="the training volumes alone (what the localiser's scenes are "
                                                     "made from; a pose run also validates on the others)")] = False,
    uncompressed: Annotated[bool, typer.Option(help="store the arrays uncompressed (for tar -cJf, which packs "
                                                    "them smaller)")] = False,
) -> None:
    """Pack the atlas volumes as .npz (numpy only: no SimpleITK needed where they are read)."""
    from model_export.atlas import pack as run
    from model_export.atlas import training_volumes

    path = run(out, root, training_volumes(root) if training_only else None, compressed=not uncompressed)
    size = sum(f.stat().st_size for f in path.iterdir())
    typer.echo(f"wrote {path} ({size / 1e6:.1f} MB)")


@app.command()
def export(
    checkpoint: PoseCheckpoint,
    output: Path,
    name: str = "default",
    version: str = "0.1.0",
    threshold: Annotated[Optional[float], typer.Option(help="variance threshold (default: calibrate now)")] = None,
    calibration_from: Annotated[Optional[Path], typer.Option(
        help="a model whose calibration (spread and accept flags) and test-time views the export takes over, "
             "for paired comparisons of a fine-tuned network before it is recalibrated")] = None,
    tta_views: Annotated[Optional[int], typer.Option(
        help="test-time views the service runs the network with: 1, 4 or 8 (default: those of "
             f"--calibration-from, else {SHIPPED_VIEWS}, as `ship`)")] = None,
    root: Root = DEFAULT_ATLAS_ROOT,
) -> None:
    """Export a checkpoint to ONNX (MC dropout kept stochastic, its draws fed from a seed) with its metadata."""
    from model_export.calibrate import calibrate as run_calibration
    from model_export.packaging import CALIBRATION, export_checkpoint
    from service.inference.model_file import load_model
    from service.inference.views import view_count

    try:
        tta_views = None if tta_views is None else view_count(tta_views)
    except ValueError as bad:
        raise typer.BadParameter(str(bad), param_hint="--tta-views") from None
    calibration, views = {}, SHIPPED_VIEWS
    if calibration_from is not None:
        if threshold is not None:
            raise typer.BadParameter("the variance threshold is part of the calibration --calibration-from takes "
                                     "over; give one or the other", param_hint="--threshold")
        info = load_model(calibration_from).info
        if tta_views is not None and tta_views != info.tta_views:
            raise typer.BadParameter(f"{calibration_from.name} was calibrated with {info.tta_views} test-time views; "
                                     f"its calibration does not hold for {tta_views}", param_hint="--tta-views")
        calibration = {k: info.metadata[k] for k in CALIBRATION if k in info.metadata}
        threshold, views = float(info.metadata["variance_threshold"]), info.tta_views
    if tta_views is not None:
        views = tta_views
    if threshold is None:
        threshold = run_calibration(checkpoint, root, views=views)["threshold"]
    path = export_checkpoint(checkpoint, output, name=name, version=version, variance_threshold=threshold,
                             tta_views=views, extra=calibration)
    exported = load_model(path)
    typer.echo(f"wrote {path} ({len(exported.draw_inputs)} dropout layers fed from seed {exported.mc_seed}, "
               f"variance threshold {threshold:.3g}, {exported.info.tta_views} test-time views)")
    if calibration_from is None:
        typer.echo("not calibrated: its variance threshold is the single-slice one, its expected errors the raw MC "
                   "spread (no mc_error_scale / shape), and it sets no max_expected_error_mm; `ship` calibrates "
                   "a model, --calibration-from takes another's calibration over for comparisons", err=True)


@app.command("fix-draws")
def fix_draws(source: PoseModel, output: Annotated[Optional[Path], typer.Argument(help="default: SOURCE itself")] = None,
              seed: int = 0) -> None:
    """Rewrite a model so that the service feeds its MC-dropout draws from SEED (a fixed ensemble: one
    request, one answer); its metadata, calibrations included, are kept."""
    import shutil

    from model_export.export import fix_draws as rewrite

    out = output or source
    if out != source:
        shutil.copyfile(source, out)
    typer.echo(f"wrote {out}: {rewrite(out, seed)} dropout layers fed from seed {seed}")


@app.command()
def evaluate(
    model: PoseModel,
    report: Annotated[Path, typer.Option(help="markdown report; figures beside it")],
    root: ValidationRoot = DEFAULT_ATLAS_ROOT,
    per_volume: int = 100,
    mc_samples: int = 100,
    acquisitions: Annotated[bool, typer.Option(help="simulated 3-stack acquisitions at every motion level (mild, moderate, "
                                                    "jumps, independent, extreme) through the server's pipeline with "
                                                    "stack consistency")] = False,
    fake: Annotated[bool, typer.Option(help="with --acquisitions: an estimator giving truth or twin + 10 mm / 10 deg "
                                            "instead of the model (tests the service's half)")] = False,
    told: Annotated[Optional[list[str]], typer.Option(help="with --acquisitions: also score each stage told this "
                                                          "slice_order (e.g. interleaved), on the same network poses")] = None,
    slices: Annotated[Optional[Path], typer.Option(help="with --acquisitions: every slice's errors, variance and "
                                                        "place in its stack, as .npz (for analyses)")] = None,
    seed: Annotated[Optional[int], typer.Option(help="[default: 12345; with --acquisitions 1]")] = None,
) -> None:
    """The paper's metrics on the model's validation volumes (those its metadata records), written as a
    markdown report."""
    if acquisitions:
        seed = 1 if seed is None else seed
        import numpy as np

        from model_export.atlas import held_out_volumes
        from model_export.evaluate_acquisitions import NoisyTwinEstimator, evaluate_acquisitions, markdown
        from service.inference.estimator import OnnxPoseEstimator
        from service.inference.model_file import load_model

        onnx = OnnxPoseEstimator(load_model(model))
        est = NoisyTwinEstimator(onnx.info, np.random.default_rng(seed)) if fake else onnx
        vols = held_out_volumes(onnx.info.metadata, root)
        summary = evaluate_acquisitions(vols, est, np.random.default_rng(seed), per_volume=max(1, per_volume),
                                        mc_samples=mc_samples, told=tuple(told or ()), slices=slices,
                                        progress=lambda line: typer.echo(line, err=True))
        report.parent.mkdir(parents=True, exist_ok=True)
        report.write_text(markdown(summary, f"Acquisitions through the pipeline: {'fake estimator' if fake else model}"))
        typer.echo(json.dumps(summary, indent=2))
        return
    from model_export.evaluate import evaluate as run

    summary = run(model, report, root, per_volume=per_volume, mc_samples=mc_samples,
                  **({} if seed is None else {"seed": seed}))
    typer.echo(json.dumps(summary, indent=2))


@app.command()
def midplane(
    root: Root = DEFAULT_ATLAS_ROOT,
    report: Annotated[Path, typer.Option(help="markdown table")] = Path("model_export/reports/midplane.md"),
) -> None:
    """Measure each atlas volume's mid-sagittal plane x0 (where it best matches its left-right mirror),
    in the atlas folder or a packed one."""
    import numpy as np

    from model_export.atlas import list_volumes, load_volumes
    from service.geometry.twin import measure_plane_x

    rows = []
    for name, population, *_ in list_volumes(root):
        vol = load_volumes([name], root)[0]                       # one at a time: .nii.gz or packed .npz
        rows.append((name, population, measure_plane_x(vol.image, vol.affine)))
        typer.echo(f"{name:24s} {population:18s} x0 = {rows[-1][2]:+.2f} mm")
    xs = np.array([r[2] for r in rows])
    lines = ["# Mid-sagittal plane of each atlas volume", "",
             "`svrnet-train midplane`: the x0 (atlas RAS mm) where the volume correlates best with its "
             "left-right mirror (`service.geometry.twin.measure_plane_x`).", "",
             "| volume | population | x0 (mm) |", "|---|---|---|"]
    lines += [f"| {n} | {p} | {x:+.2f} |" for n, p, x in rows]
    lines += ["", f"Median over all {len(xs)} volumes: {np.median(xs):+.2f} mm; range {xs.min():+.2f} to "
              f"{xs.max():+.2f} mm. Models are trained and served with the plane at the median."]
    report.write_text("\n".join(lines) + "\n")


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
def quantise(
    source: PoseModel,
    output: Path,
    slices: Annotated[int, typer.Option(help="simulated training slices that calibrate the activation ranges")] = 1024,
    seed: int = 0,
    root: Root = DEFAULT_ATLAS_ROOT,
) -> None:
    """Write a model with int8 convolutions (head and MC dropout float), its metadata kept; then run
    `calibrate-spread` and `calibrate-acceptance` on it: the spread and the accept flags are
    calibrated on the poses of the file served."""
    from model_export.quantise import quantise_model

    path = quantise_model(source, output, slices, seed, root)
    typer.echo(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB; {source.stat().st_size / 1e6:.1f} MB before)")
    typer.echo("its calibrations are the float model's: run `calibrate-spread`, then `calibrate-acceptance`, then "
               "`calibrate-noise`, then `calibrate-frame`, on it", err=True)


@app.command()
def ship(
    checkpoint: PoseCheckpoint,
    out: Annotated[Path, typer.Option(help="model folder the service reads (SVRNET_MODELS_DIR/<name>)")],
    name: str = "default",
    version: str = "1.0.0",
    comparison: Annotated[Optional[Path], typer.Option(help="table.json of `compare`")] = None,
    report: Annotated[Optional[Path], typer.Option(
        help="the evaluation report (beside it: its figures, acceptance.md, noise.md and frame.md) [default: OUT/report.md]")] = None,
    force: Annotated[bool, typer.Option(help="replace a model folder that holds files")] = False,
    root: ValidationRoot = DEFAULT_ATLAS_ROOT,
    tta_views: Annotated[int, typer.Option(help="test-time views the MC samples are shared among: 1, 4 "
                                                "(rotations) or 8 (rotations and flips)")] = SHIPPED_VIEWS,
    int8: Annotated[bool, typer.Option("--int8/--float", help="int8 convolutions (`quantise`) before the "
                                                              "calibrations, which then measure the file served")] = True,
    slices_per_volume: Annotated[Optional[int], typer.Option(
        min=1, help="validation slices per volume of the threshold's and the spread's calibrations and of the "
                    "evaluation [default: theirs, 120 / 60 / 100]: fewer for a quick look, not for a model to serve")] = None,
    acceptance_per_volume: Annotated[Optional[int], typer.Option(
        min=1, help="acquisitions per validation volume and motion level of the accept flags [default: 8]")] = None,
    quant_slices: Annotated[Optional[int], typer.Option(min=16, help="slices calibrating the int8 ranges "
                                                                     "[default: 1024]")] = None,
    noise_per_volume: Annotated[Optional[int], typer.Option(
        min=0, help="acquisitions per validation volume, noise level, pixel size and motion level of the noise "
                    "error [default: 2; 0: not calibrated]")] = None,
    frame_per_volume: Annotated[Optional[int], typer.Option(
        min=0, help="acquisitions per validation volume and motion level of the frame error, beside its "
                    "whole-uterus requests [default: 2; 0: not calibrated]")] = None,
) -> None:
    """Calibrate, export, evaluate and write the model card: the folder the service loads (the MC
    spread's expected error calibrated as `calibrate-spread` does, then the accept flags on the
    pipeline's final poses, as `calibrate-acceptance` does, then the noise error, as
    `calibrate-noise` does, and the frame error, as `calibrate-frame` does). The folder is built beside ``out`` and
    takes its place only when whole: a server never finds a model without its calibration or card."""
    from model_export.packaging import load_checkpoint
    from model_export.shipping import ship_folder, ship_into

    if out.exists() and any(out.iterdir()) and not force:
        raise typer.BadParameter(f"{out} holds a model already; --force replaces it", param_hint="--out")
    try:
        _, ck = load_checkpoint(checkpoint)
    except (KeyError, ValueError, OSError) as bad:
        raise typer.BadParameter(f"not a pose-network checkpoint ({bad})", param_hint="CHECKPOINT") from None
    budget = {"slices": slices_per_volume, "acquisitions": acceptance_per_volume, "quant": quant_slices,
              "noise": noise_per_volume, "frame": frame_per_volume}
    evaluation = ship_folder(out, report, lambda staging, written, shown: ship_into(
        staging, out, checkpoint, ck, name, version, comparison, written, shown, root, tta_views, int8,
        {k: v for k, v in budget.items() if v is not None}, typer.echo))
    typer.echo(json.dumps(evaluation, indent=2))


if __name__ == "__main__":
    app()
