"""The model card (markdown) of a shipped model, written from the measured artefacts."""

from __future__ import annotations

import json
from pathlib import Path

from model_export.atlas import POPULATIONS
from model_export.compare import markdown as table_markdown
from model_export.training_record import commits

SHIPPED_SCALE_SAMPLES = 1_000_000
"""Training samples (all stages) under which a card calls its model a quick look: the shipped models
are trained on several millions (each model's card states its own budget)."""


def budget_text(train_summary: dict, train_config: dict, budget: list[tuple[str, int | None, int]] | None = None) -> str:
    """The card's opening statement of what made the model: its training (steps of the last stage,
    samples and hours over all stages) and the budgets of its calibrations and evaluation
    (``(what, given, default)``; ``given`` None: the default), and **quick look** when the training
    is under :data:`SHIPPED_SCALE_SAMPLES` or a budget under its default.

    Example:
        >>> print(budget_text({"steps": 4, "samples_seen": 64, "train_seconds": 36.0}, {"batch": 16},
        ...                   [("slices per volume of the evaluation", 7, 100), ("slices of the int8 ranges", None, 1024)]))
        **Budget**: training 4 steps of batch 16 in its last stage, 64 samples in 0.01 h over all stages; 7 slices per volume of the evaluation (default 100), 1024 slices of the int8 ranges.
        <BLANKLINE>
        **Quick look**: under the scale of a model to serve (training under 1,000,000 samples; the slices per volume of the evaluation under its default): its figures and calibrations show that the recipe runs, not what it achieves, and it is not for serving.
    """
    totals = train_summary.get("totals") or {}
    samples = int(totals.get("samples", train_summary.get("samples_seen", 0)))
    hours = float(totals.get("hours", train_summary.get("train_seconds", 0.0) / 3600))
    parts = [f"{given if given is not None else default} {what}" + (f" (default {default})" if given is not None and
                                                                      given != default else "")
             for what, given, default in budget or []]
    text = (f"**Budget**: training {train_summary['steps']} steps of batch {train_config.get('batch', '?')} in its last "
            f"stage, {samples:,} samples in {hours:.2f} h over all stages{'; ' if parts else ''}{', '.join(parts)}.")
    short = ([f"training under {SHIPPED_SCALE_SAMPLES:,} samples"] if samples < SHIPPED_SCALE_SAMPLES else []) + \
        [f"the {what} under its default" for what, given, default in budget or [] if given is not None and given < default]
    if not short:
        return text
    return (f"{text}\n\n**Quick look**: under the scale of a model to serve ({'; '.join(short)}): its figures and "
            "calibrations show that the recipe runs, not what it achieves, and it is not for serving.")


def _commit_text(info: dict, train_summary: dict) -> str:
    """The code's commit at export and at every training run behind the checkpoint (``-dirty``: the
    working tree held uncommitted changes to tracked files, which the commit alone does not give).

    Example:
        >>> _commit_text({"commit": "e4f5a6b"}, {"history": [{"commits": ["a1b2c3d-dirty"]}]})
        'e4f5a6b at export; training at a1b2c3d-dirty (-dirty: with uncommitted changes to tracked files)'
        >>> _commit_text({"commit": "e4f5a6b"}, {"history": [{"samples": 10}]})
        'e4f5a6b at export; training: not recorded'
    """
    trained = commits(train_summary.get("history", []))
    text = f"{info['commit']} at export; " + (f"training at {', '.join(trained)}" if trained else "training: not recorded")
    if any(c.endswith("-dirty") for c in [info["commit"], *trained]):
        text += " (-dirty: with uncommitted changes to tracked files)"
    return text


def _grid_text(train_config: dict) -> str:
    grid, channels = train_config.get("spatial_grid", 0), train_config.get("grid_channels", 0)
    if not grid:
        return "global average pooled features"
    reduce = f"1x1 convolution to {channels} channels, then " if channels else ""
    return f"{reduce}a {grid}x{grid} spatial grid of features"


def _criterion_text(cal: dict) -> str:
    """Why the threshold was chosen for another error than 10 mm, when it was."""
    criterion = cal.get("criterion_mm", cal["error_mm"])
    if criterion == cal["error_mm"]:
        return ""
    return (f"So few slices fall on one side of {cal['error_mm']:.0f} mm that the threshold is chosen for "
            f"the median error, {criterion:.1f} mm, instead (AUROC {cal['auroc_criterion']:.3f}): it "
            "separates this model's better half of the slices from its worse half.")


def _comparison_text(comparison: list[dict] | None) -> str:
    """The Table II rows with the budget they were trained on."""
    if not comparison:
        return ("not rerun for this model: the six backbones at an equal short budget are in the card of "
                "v1.0.0 (the git history of this file)")
    r = comparison[0]
    return (f"Each backbone: {r['steps']} steps of batch {r['batch']} ({r['steps'] * r['batch']:,} samples), width "
            f"{r['width']}, the same data stream and validation slices (`svrnet-train compare`). At this budget "
            "no backbone gets far from predicting the average pose (compare the default above, trained "
            "about 70x longer); the table shows their cost -- parameters, training time, inference speed "
            "on this CPU -- more than their eventual accuracy.\n\n" + table_markdown(comparison))


def _stage_text(train_config: dict) -> str:
    """The first stage's figures when the run started from another checkpoint's weights (``--init``)."""
    prior = train_config.get("init_from")
    if not prior:
        return ""
    if "distil" in prior:
        return (f"; the trunk distilled from `{prior['checkpoint']}` (width {train_config['width']}: its features and "
                "grid points matched in all eight test-time views; the head is the teacher's, frozen) -- the cost "
                "below is the total of the teacher's stages and the distillation")
    if "whole_network" not in prior:          # a checkpoint without a training history
        return (f"; a second stage, started from the weights of a first run of {prior['steps']} steps "
                f"({prior['samples_seen']:,} samples, {prior['train_seconds'] / 3600:.2f} h, val E.D. "
                f"{prior['val_ed_mm']:.1f} mm) with the same recipe -- the cost below is the total of both")
    part = "all its weights" if prior["whole_network"] else "its trunk (a new head for the new label)"
    return (f"; the last of the stages below, started from {part} of the previous stage's checkpoint "
            f"({prior['samples_seen']:,} samples, {prior['train_seconds'] / 3600:.2f} h) -- the cost below is the "
            "total of all stages")


LABEL_TEXT = {
    "anchor": "anchor points (P1, P2, P3 at +-60 mm; one L2 term per point)",
    "grid": "grid of 8 x 8 plane points over +-60 mm (atlas mm of each; pose by a weighted Kabsch fit)",
}
LOSS_TEXT = {
    "l2": "plain L2 (the average of the left-right twins is what it learns)",
    "min": "mirror-aware: the distance to the nearer of the label and its left-right twin",
    "invariant": "mirror-aware by construction: (y, z) of each point directly, the x offsets from the symmetry plane "
                 "through their sign-invariant outer product; the branch is left to the stack",
}


def _label_text(info: dict, train_config: dict) -> str:
    label = LABEL_TEXT.get(info["label_type"], info["label_type"])
    return f"{label}; loss {LOSS_TEXT.get(train_config.get('loss', 'l2'), train_config.get('loss'))}"


def _totals_text(train_summary: dict) -> str:
    """Samples and hours of every training stage behind the checkpoint, per hardware."""
    totals = train_summary.get("totals")
    if not totals:
        hours = train_summary["train_seconds"] / 3600
        return f"- cost: **{hours:.2f} h**, **{train_summary['samples_seen']:,} samples seen** (hardware not recorded)"
    rows = "\n".join(f"| {hw} | {d['samples']:,} | {d['hours']:.2f} |" for hw, d in totals["by_hardware"].items())
    stages = "\n".join(f"| {i + 1} | {seg.get('label_type', '?')} | {seg.get('loss', '?')} | {seg['hardware']} | "
                       f"{seg['samples']:,} | {seg['seconds'] / 3600:.2f} |"
                       for i, seg in enumerate(train_summary.get("history", [])))
    stage_table = ("\n\n| stage | label | loss | hardware | samples | hours |\n|---|---|---|---|---|---|\n" + stages
                   if stages else "")
    return (f"- totals over all stages (training compounds: each run starts from the previous checkpoint): "
            f"**{totals['samples']:,} samples**, **{totals['hours']:.2f} h**\n\n"
            f"| hardware | samples | hours |\n|---|---|---|\n{rows}{stage_table}")


def _accepted_twin(evaluation: dict) -> str:
    v = evaluation.get("ed_twin_accepted_mean_mm")
    return "" if v is None else f", twin-min {v:.2f} mm"


def _schedule_text(train_config: dict, steps: int, best: bool = False) -> str:
    if "distil" in train_config:                       # model_export.distil: warm-up, cosine over a time budget
        d = train_config["distil"]
        return (f"lr {d['lr']}, {d['warmup_steps']} warm-up steps then a cosine over {d['minutes']} min "
                f"({steps} steps)")
    planned = int(train_config.get("steps", steps))
    stopped = ""
    if best and steps < planned:
        stopped = f" (this is the checkpoint of step {steps}, the best of the run on the validation slices)"
    elif steps < planned:
        stopped = f" (stopped at step {steps} by its time budget)"
    if not train_config.get("lr_milestones"):
        return f"constant lr {train_config['lr']}, {planned} steps{stopped}"
    return (f"lr {train_config['lr']}, step decay x{train_config['lr_gamma']} at {train_config['lr_milestones']} of "
            f"{planned} steps{stopped}")


def _twin_rows(evaluation: dict) -> str:
    if "ed_twin_mean_mm" not in evaluation:
        return ""
    return (f"\n| twin-min E.D. (nearer of truth and twin) | **{evaluation['ed_twin_mean_mm']:.2f} mm** |\n"
            f"| twin-min median / p90 | {evaluation['ed_twin_median_mm']:.2f} / {evaluation['ed_twin_p90_mm']:.2f} mm |\n"
            f"| slices under 10 mm: truth / twin-min | {100 * evaluation['ed_under_10mm']:.1f} % / "
            f"{100 * evaluation['ed_twin_under_10mm']:.1f} % |\n"
            f"| slices nearer the twin than the truth | {100 * evaluation['on_twin_fraction']:.1f} % |")


def _tz_text(train_config: dict) -> str:
    from model_export.simulate import FULL_EXTENT_TZ_FRACTION   # the default when the run changed nothing

    fraction = float((train_config.get("simulation") or {}).get("tz_fraction", FULL_EXTENT_TZ_FRACTION))
    return f"the central {200 * fraction:.0f} %"


def _simulation_text(train_config: dict) -> str:
    """The run's own simulation settings beyond the defaults (``TrainConfig.simulation``), as the card states them.

    Example:
        >>> _simulation_text({"simulation": {"surroundings_share": 0.3, "tz_fraction": 0.5}})
        '; settings of this run: `surroundings_share` 0.3'
        >>> _simulation_text({})
        ''
    """
    own = {k: v for k, v in (train_config.get("simulation") or {}).items() if k != "tz_fraction"}   # stated above
    return "; settings of this run: " + ", ".join(f"`{k}` {v}" for k, v in sorted(own.items())) if own else ""


def _threshold_text(info: dict, cal: dict) -> str:
    """The served variance threshold, and the single-slice one when the accept flags' calibration
    on the pipeline's final poses replaced it.

    Example:
        >>> print(_threshold_text({"variance_threshold": "447.2"}, {"threshold": 48.35}))
        447.2 (calibrated on the pipeline's final poses, see "Accept flags"; 48.35 on single slices, see below)
        >>> print(_threshold_text({"variance_threshold": "48.35"}, {"threshold": 48.35}))
        48.35 (calibrated on single slices, see below)
    """
    served, single = float(info["variance_threshold"]), float(cal["threshold"])
    if abs(served - single) <= 1e-6 * max(abs(single), 1.0):
        return f"{served:.4g} (calibrated on single slices, see below)"
    return (f"{served:.4g} (calibrated on the pipeline's final poses, see \"Accept flags\"; "
            f"{single:.4g} on single slices, see below)")


def _views_text(info: dict) -> str:
    n = int(info.get("tta_views", 1))
    what = {1: "the image only", 4: "its 4 rotations by 90 degrees", 8: "its 4 rotations, with and without a left-right flip"}
    return (f"{n}: {what.get(n, '')}; the MC samples are shared among them, each view's poses mapped back exactly "
            "(`service/inference/views.py`)")


def _measured_text(cal: dict) -> str:
    """What the single-slice threshold was measured on: the file served, or the float network.

    Example:
        >>> _measured_text({"measured_on": "model.onnx"})
        '`model.onnx`, the file served'
    """
    where = cal.get("measured_on")
    return f"`{where}`, the file served" if where and where.endswith(".onnx") else "the checkpoint's float network"


def draws_text(info: dict) -> str:
    """The card's row on where the MC-dropout draws come from.

    Example:
        >>> draws_text({"mc_seed": "0"})[:48]
        'fixed (seed 0): pass k of view v always drops th'
    """
    if "mc_seed" not in info:
        return "drawn afresh in the graph at every call (onnxruntime `RandomUniformLike`)"
    return (f"fixed (seed {info['mc_seed']}): pass k of view v always drops the same units, fed by the service "
            "(`svrnet-train fix-draws`); a slice's network input gets the same samples in any call, and a request one answer")


USE_AND_LIMITS = """## Intended use

Research use only (the CRL atlas's licence); not for clinical decisions. Input: the slices of
fetal brain T2-weighted single-shot stacks (2-4.5 mm slices, 0.8-1.6 mm pixels; trained on brains of
21-38 weeks' gestation), each with its brain mask or the service's localiser's. Output: each slice's
rigid pose in the atlas space with an expected error. Use it through the service: a single slice's
pose (the validation below) is a coarse start; a request of several stacks, judged by their stack
and request stages, is what the accept flags (the last sections) are calibrated on, and their table
gives what such a request achieves at each motion level against the truth and twin-min.

## Limitations

- The atlas frame of an unseen brain: a held-out simulated brain is placed 1-3 degrees and 1-2 mm
  off its true frame, the same for every slice of it; a real brain differs by several degrees from
  an age-matched atlas volume. `expected_error_mm` does not include that common offset.
- A single slice cannot tell its left-right mirror twin from the truth; a stack decides its slices'
  side. Errors are given against the truth and twin-min.
- Calibrated on simulated requests of three stacks: a stack sent alone, a signal void over the
  brain, another contrast or an image that is no fetal brain are posed worse than the expected error
  says (docs/accuracy.md, "Real scans" and "Other scanners' acquisitions").
- Planes near the brain's ends are the hardest: the validation below takes planes in the central
  70 % of the brain's extent; over its whole extent the single-slice twin-min error is about twice
  as large (docs/accuracy.md, "By depth").
- It learnt the atlas's brain masks, which leave out most extra-axial CSF: a mask drawn to the
  skull's inside is sent with `masks_hold_csf` (the service insets it by 2 mm).
"""
"""The card's use and limits, the same for every pose model of this recipe."""


def write_card(out: Path, *, info: dict, train_summary: dict, train_config: dict, calibration: dict,
               evaluation: dict, comparison: list[dict] | None, report_path: str, onnx_bytes: int,
               budget: list[tuple[str, int | None, int]] | None = None) -> Path:
    """Write ``card.md`` with its budget first (:func:`budget_text`), then the training cost,
    validation accuracy, calibration and the backbone table."""
    cal = {k: v for k, v in calibration.items() if not isinstance(v, list)}
    text = f"""# Model card: SVRnet `{info['name']}` {info['version']}

{budget_text(train_summary, train_config, budget)}

| | |
|---|---|
| backbone | `{info['backbone']}` (width {train_config['width']}), {_grid_text(train_config)}, head FC-{train_config['hidden']} with one output branch per label component, dropout {train_config['dropout']} before every FC layer |
| labels | {_label_text(info, train_config)} |
| input | {info['input_size']} x {info['input_size']} px of {info['pixel_spacing_mm']} mm; {info['intensity']} |
| output space | atlas `{info['atlas_id']}` (RAS mm of `shared/data/fetal_atlas`) |
| variance threshold | {_threshold_text(info, cal)} |
| test-time views | {_views_text(info)} |
| arithmetic | {info.get('quantised', 'float32')} |
| MC draws | {draws_text(info)} |
| file | `model.onnx` ({onnx_bytes / 1e6:.1f} MB), `checkpoint.pt` (the next training run starts from it: `svrnet-train train --init`) |
| commit | {_commit_text(info, train_summary)} |

{USE_AND_LIMITS}
## Training

- data: {train_summary.get('train_volumes_text', '')}
- simulation: thick slices (2-4.5 mm Gaussian PSF), 0.8-1.5 mm acquisition pixels, any orientation
  (uniform normals, 0-360 degree in-plane), Tz over {_tz_text(train_config)} of the brain's extent, +-10 % brain size,
  bias field, gamma, signal voids, Rician noise, perturbed masks; then the service's own slice
  preprocessing (`service/preprocess/slices.py`){_simulation_text(train_config)}.
- optimiser: Adam, {_schedule_text(train_config, train_summary['steps'], train_summary.get('best_checkpoint', False))}, batch {train_config['batch']}{_stage_text(train_config)}
{_totals_text(train_summary)}

## Validation (whole held-out volumes: {', '.join(train_config['val_volumes'])})

3 mm thick, 1 mm pixels, Rician noise 3 %, bias field, any orientation, planes in the central 70 %
of the brain's extent; 100 MC-dropout passes (shared among the test-time views, as the service runs
it); single slices, before any stack or request stage; full report:
`{report_path}`.

| metric | value |
|---|---|
| mean anchor-point E.D. (against the truth) | **{evaluation['ed_mean_mm']:.2f} mm** |
| median / p90 E.D. | {evaluation['ed_median_mm']:.2f} / {evaluation['ed_p90_mm']:.2f} mm |{_twin_rows(evaluation)}
| geodesic distance (mean) | {evaluation['gd_mean']:.2f} |
| 3-MAD outliers | {100 * evaluation['outlier_fraction']:.1f} % |
| AUROC of geodesic variance for {'twin-min ' if 'ed_twin_mean_mm' in evaluation else ''}E.D. > 10 mm | {evaluation['auroc_variance_error_gt_10mm']:.3f} |
| accepted at the single-slice threshold ({cal['threshold']:.4g}) | {100 * evaluation['accepted_fraction']:.1f} %, their mean E.D. {evaluation['ed_accepted_mean_mm']:.2f} mm{_accepted_twin(evaluation)} |

## Calibration of the single-slice variance threshold

On {cal['n_slices']} slices of the validation volumes simulated with the full training corruptions, measured on
{_measured_text(cal)},
{100 * cal['bad_fraction']:.0f} % of the slices have {'twin-min ' if cal.get('errors') == 'twin-min' else ''}E.D. > {cal['error_mm']:.0f} mm (MC samples put on one branch first); the AUROC of variance for
flagging them is {cal['auroc']:.3f}. {_criterion_text(cal)} The threshold maximising Youden's J for
flagging slices with E.D. > {cal.get('criterion_mm', cal['error_mm']):.1f} mm is **{cal['threshold']:.4g}** (the paper
found ~10 on its data); Spearman correlation of variance and error {cal['spearman_variance_error']:.2f};
accepted {100 * cal['accepted_fraction']:.0f} % with mean E.D. {cal['ed_accepted_mean_mm']:.1f} mm vs
{cal['ed_rejected_mean_mm']:.1f} mm for rejected ones.

## The six backbones of the paper (equal short budget, small width)

{_comparison_text(comparison)}

## Data and licences

{chr(10).join(f"- `{k}`: {v}" for k, v in POPULATIONS.items())}

Because of the CRL atlas licence, this model is for **non-commercial research use only**.
"""
    out.write_text(text)
    return out


def load_json(path: Path) -> dict | list:
    return json.loads(Path(path).read_text())
