"""``svrnet-train ship``'s steps: export, quantise, calibrate the variance threshold, calibrate the
spread, evaluate, calibrate the accept flags, the noise error and the frame error, and write the model card, each into
the folder being built. Every calibration and the evaluation measure the file shipped (int8 where it
is), on the checkpoint's own validation volumes.

The command (`svrnet-train ship`, :func:`model_export.cli.ship`) builds that folder beside the one it replaces and puts it
in place only when every step is done: a server never finds a model without its calibration or card.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

STEP_SLICES = {"variance threshold": 120, "spread": 60, "evaluation": 100}
"""Each step's own validation slices per volume (``calibrate``, ``calibrate_spread``, ``evaluate``),
which ``ship --slices-per-volume`` replaces in all three."""


def budgets(budget: dict[str, int], int8: bool) -> list[tuple[str, int | None, int]]:
    """``(what, given, default)`` of every sample count of `ship`'s steps, for the card's budget
    (:func:`~model_export.card.budget_text`); ``given`` None where ``budget`` leaves it to the step.

    Example:
        >>> [row[1:] for row in budgets({"slices": 7, "noise": 0}, int8=False)]
        [(7, 120), (7, 60), (7, 100), (None, 8), (0, 2), (None, 2)]
    """
    from model_export import calibrate_frame, calibrate_noise
    from model_export.calibrate_acceptance import PER_VOLUME
    from model_export.quantise import CALIBRATION_SLICES

    rows = [(f"validation slices per volume of the {step}", budget.get("slices"), n) for step, n in STEP_SLICES.items()]
    rows.append(("acquisitions per validation volume and motion level of the accept flags", budget.get("acquisitions"),
                 PER_VOLUME))
    if int8:
        rows.append(("slices of the int8 ranges", budget.get("quant"), CALIBRATION_SLICES))
    rows.append(("acquisitions per validation volume and setting of the noise error", budget.get("noise"),
                 calibrate_noise.PER_VOLUME))
    rows.append(("acquisitions per validation volume and motion level of the frame error", budget.get("frame"),
                 calibrate_frame.PER_VOLUME))
    return rows


def ship_folder(out: Path, report: Path | None, build: Callable[[Path, Path, Path], dict]) -> dict:
    """Build the model folder ``out`` beside it (``.<name>.shipping``) with ``build(staging, report,
    shown_report)`` and put it in place of ``out`` whole; on any failure remove what was built. A
    ``report`` inside ``out`` (default: ``out/report.md``) is written into the folder being built and
    named by where it will be (``shown_report``). Returns what ``build`` returns."""
    staging = out.parent / f".{out.name}.shipping"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    report = report if report is not None else out / "report.md"
    if report.resolve().is_relative_to(out.resolve()):       # written with the folder, not into the one it replaces
        shown_report, report = report, staging / report.resolve().relative_to(out.resolve())
        report.parent.mkdir(parents=True, exist_ok=True)
    else:
        shown_report = report
    try:
        result = build(staging, report, shown_report)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)             # nothing half-made is left for a server to find
        raise
    old = out.parent / f".{out.name}.replaced"
    shutil.rmtree(old, ignore_errors=True)
    if out.exists():
        out.rename(old)
    staging.rename(out)
    shutil.rmtree(old, ignore_errors=True)
    return result


def ship_into(staging: Path, out: Path, checkpoint: Path, ck: dict, name: str, version: str,
              comparison: Path | None, report: Path, shown_report: Path, root: Path, tta_views: int,
              int8: bool, budget: dict[str, int], say: Callable[[str], object] = print) -> dict:
    """`ship`'s steps, each writing into ``staging``, which becomes ``out``; the evaluation's summary.
    ``budget``: the sample counts given (``slices`` per volume, accept-flag ``acquisitions`` per
    volume and level, ``quant`` slices, ``noise`` acquisitions per volume and setting); the others are
    each step's own. ``say``: where each step's progress goes."""
    from model_export.calibrate import calibrate as run_calibration
    from model_export.card import load_json, write_card
    from model_export.evaluate import evaluate as run_evaluation
    from model_export.packaging import export_checkpoint
    from model_export.spread import write_metadata
    from service.inference.model_file import load_model

    per_volume = {"per_volume": budget["slices"]} if "slices" in budget else {}
    onnx_path = export_checkpoint(checkpoint, staging / "model.onnx", name=name, version=version,
                                  variance_threshold=float("nan"), tta_views=tta_views)    # calibrated below
    if int8:
        from model_export.quantise import quantise_model

        quantise_model(onnx_path, onnx_path, root=root, **({"count": budget["quant"]} if "quant" in budget else {}))
    cal = run_calibration(checkpoint, root, model_file=onnx_path, **per_volume)
    write_metadata(onnx_path, {"variance_threshold": cal["threshold"]})
    say(f"calibrated variance threshold {cal['threshold']:.4g} (AUROC {cal['auroc']:.3f}) on {onnx_path.name}"
        f"{' (int8)' if int8 else ''}")
    shutil.copyfile(checkpoint, staging / "checkpoint.pt")
    from model_export.spread import calibrate_spread as run_spread

    say(f"spread calibrated: {json.dumps(run_spread(onnx_path, root, **per_volume))}")
    evaluation = run_evaluation(onnx_path, report, root, **per_volume)
    if report.exists():                                                        # the model's path once in place
        report.write_text(report.read_text().replace(str(staging), str(out)))
    from model_export.training_record import prior_history, totals

    summary = {"train_seconds": ck["train_seconds"], "samples_seen": ck["samples_seen"], "steps": ck["step"],
               "best_checkpoint": ck.get("val_twin_ed_mm") is not None and ck.get("val_twin_ed_mm") == ck.get("best_ed_mm"),
               "totals": totals(prior_history(ck)), "history": prior_history(ck),
               "train_volumes_text": f"{len(ck['config']['train_volumes'])} atlas volumes: "
                                     + ", ".join(ck["config"]["train_volumes"])}
    from model_export.atlas import held_out_volumes
    from model_export.calibrate_acceptance import PER_VOLUME, flag_metadata, measure, markdown as acceptance_markdown
    from service.inference.estimator import OnnxPoseEstimator

    held_out = held_out_volumes(ck, root)             # loaded once: the accept flags, the noise and frame errors
    acquisitions = budget.get("acquisitions", PER_VOLUME)
    say(f"accept flags: {acquisitions} acquisitions per validation volume and motion level through every stage")
    flags = measure(OnnxPoseEstimator(load_model(onnx_path)), held_out, per_volume=acquisitions)
    write_metadata(onnx_path, flag_metadata(flags))
    noise_table = ""
    if budget.get("noise", 1):
        from model_export import calibrate_noise

        say("noise error: acquisitions at a ladder of noise levels and two pixel sizes through every stage")
        noise = calibrate_noise.calibrate(calibrate_noise.measure(
            OnnxPoseEstimator(load_model(onnx_path)), held_out,
            budget.get("noise", calibrate_noise.PER_VOLUME)))
        write_metadata(onnx_path, calibrate_noise.noise_metadata(noise))
        noise_table = calibrate_noise.markdown(noise)
        (report.parent / "noise.md").write_text(f"# Noise error of {name} {version}\n\n{noise_table}\n")
    frame_table = ""
    if budget.get("frame", 1):
        from model_export import calibrate_frame

        say("frame error: acquisitions and whole-uterus requests (the localiser's masks and the atlas's) through every stage")
        frame = calibrate_frame.calibrate(calibrate_frame.measure(
            OnnxPoseEstimator(load_model(onnx_path)), held_out, budget.get("frame", calibrate_frame.PER_VOLUME)))
        write_metadata(onnx_path, calibrate_frame.frame_metadata(frame))
        frame_table = calibrate_frame.markdown(frame)
        (report.parent / "frame.md").write_text(f"# Frame error of {name} {version}\n\n{frame_table}\n")
    info = load_model(onnx_path).info.metadata
    write_card(staging / "card.md", info=info, train_summary=summary, train_config=ck["config"], calibration=cal,
               evaluation=evaluation, comparison=load_json(comparison) if comparison else None,
               report_path=str(shown_report), onnx_bytes=onnx_path.stat().st_size, budget=budgets(budget, int8))
    card = staging / "card.md"
    card.write_text(card.read_text() + "\n" + acceptance_markdown(flags, "Accept flags").replace("# Accept", "## Accept", 1)
                    + (f"\n## Noise error\n\n{noise_table}\n" if noise_table else "")
                    + (f"\n## Frame error\n\n{frame_table}\n" if frame_table else ""))
    (report.parent / "acceptance.md").write_text(acceptance_markdown(flags, f"Accept flags of {out / 'model.onnx'}"))
    (staging / "calibration.json").write_text(json.dumps(cal))
    return evaluation
