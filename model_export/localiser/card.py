"""The localiser's model card, written from what was shipped: the model file's metadata, the
checkpoint's record of its training (:mod:`model_export.localiser.record`) and the measured figures.

Nothing in the card is fixed text about one version: the version, budgets, seed, data and
commits are those ``ship`` was given and read, and a run on small budgets is marked a quick look
(:func:`quick_look`). The history of the shipped versions is in ``docs/reports/training-runs.md``.

Example (a 3-step run on 2 shards is no model to use):
    >>> quick_look({"steps": 3, "shards": 2, "heldout_stacks": 40, "pose_scenes": 10})
    ['3 training steps', '2 training shards']
"""

from __future__ import annotations

import shlex
from pathlib import Path

import numpy as np
import onnxruntime as ort

from service.preprocess.localisation import POSE_MASK_INSET_MM

QUICK_LOOK = {"steps": 1000, "shards": 100, "heldout_stacks": 20, "pose_scenes": 5}
"""Budgets under which a card is a quick look: training steps, training shards, held-out stacks
measured, whole-uterus scenes of known poses measured."""

_NAMES = {"steps": "training steps", "shards": "training shards", "heldout_stacks": "held-out stacks",
          "pose_scenes": "pose scenes"}


def _fmt(x: float | None, digits: int = 3) -> str:
    return "—" if x is None or (isinstance(x, float) and np.isnan(x)) else f"{x:.{digits}f}"


def quick_look(budgets: dict) -> list[str]:
    """The budgets of ``budgets`` below :data:`QUICK_LOOK`, said in words (none: a full run; a budget
    that is not known, None, is not judged)."""
    return [f"{budgets[k]} {_NAMES[k]}" for k, least in QUICK_LOOK.items() if budgets.get(k) is not None
            and budgets[k] < least]


def budgets(figures: dict) -> dict:
    """Steps done, training shards, held-out stacks and pose scenes of ``figures`` (as
    :func:`~model_export.localiser.evaluate.measure` gives them, with ``shipped``; None: not known)."""
    shipped, s = figures.get("shipped") or {}, figures["summary"]
    return {"steps": shipped.get("step"), "shards": shipped.get("shards"),
            "heldout_stacks": s["heldout_stacks"], "pose_scenes": s.get("pose_scenes")}


def _budget_words(training: dict | None, steps_done: int) -> str:
    if training and training.get("steps") is not None:
        return f"{training['steps']} steps, reproducible"
    if training and training.get("minutes") is not None:
        return f"{training['minutes']:g} minutes of wall clock, not reproducible ({steps_done} steps on that machine)"
    return "not recorded"


def reproduce_command(training: dict, config: dict) -> str:
    """The command that repeats a recorded run (``python -m model_export.localiser.train``).

    Example:
        >>> print(reproduce_command({"data": {"folder": "T"}, "steps": 3, "seed": 1, "lr": 0.002, "batch": 4,
        ...     "crop": 32, "threads": 1, "device": "cpu", "loaders": 0}, {"width": 4, "depth": 2, "in_channels": 3}))
        python -m model_export.localiser.train --data T --out checkpoint.pt --steps 3 --seed 1 --width 4 --depth 2 --channels 3 --lr 0.002 --batch 4 --crop 32 --device cpu --loaders 0 --threads 1
    """
    budget = ["--steps", training["steps"]] if training.get("steps") is not None else ["--minutes", training["minutes"]]
    words = ["python", "-m", "model_export.localiser.train", "--data", training["data"]["folder"], "--out",
             "checkpoint.pt", *budget, "--seed", training["seed"], "--width", config["width"], "--depth",
             config["depth"], "--channels", config["in_channels"], "--lr", training["lr"], "--batch",
             training["batch"], "--crop", training["crop"]]
    if training.get("init"):
        words += ["--init", training["init"]["name"]]
    if training.get("teacher"):
        words += ["--teacher", training["teacher"]["name"], "--teacher-weight", training["teacher_weight"]]
    if training.get("freeze_norm"):
        words.append("--freeze-norm")
    words += ["--device", training["device"], "--loaders", training["loaders"], "--threads", training["threads"]]
    return " ".join(shlex.quote(str(w)) for w in words)


def _file(record: dict | None) -> str:
    return "—" if not record else f"`{record['name']}`, sha256 `{record['sha256']}`"


def _training_data(shipped: dict) -> str:
    data = (shipped.get("training") or {}).get("data")
    if not data:
        return (f"The checkpoint records no data set ({shipped.get('shards', 'no')} shards, by its count): it was "
                "trained before checkpoints recorded their shards.\n")
    rows = "\n".join(f"| {g['settings'].get('style', '—')} | {g['seeds']} | {g['shards']} | "
                     f"{len(g['settings'].get('volumes', []))} | {g['settings'].get('shading_share', '—')} | "
                     f"{g['settings'].get('faint_skull_share', '—')} | {g['settings'].get('motion') or 'drift'} | "
                     f"`{g['settings'].get('commit', '—')}` |" if g["settings"] else
                     f"| not recorded | {g['seeds']} | {g['shards']} | | | | | |" for g in data["generators"])
    return f"""The shard folder `{data['folder']}` as training ended: {data['shards']} shards, from `{data['names'][0] if data['names'] else '—'}`
to `{data['names'][-1] if data['names'] else '—'}` (manifest sha256 `{data['manifest_sha256']}`: one `name sha256`
line per shard). Generator settings, as the shards record them:

| style | seeds | shards | atlas volumes | shading share | faint-skull share | motion | generator commit |
|---|---|---|---|---|---|---|---|
{rows}
"""


def _made(shipped: dict, meta: dict) -> str:
    training, ckpt = shipped.get("training"), shipped.get("checkpoint") or {}
    where = ("`checkpoint.pt` beside this card" if ckpt.get("copied") else
             "not shipped (too large to copy)" if ckpt else "—")
    lines = [("checkpoint", f"{where}; {ckpt.get('bytes', 0) / 2**20:.1f} MB, sha256 `{ckpt.get('sha256', '—')}`"),
             ("network", meta["architecture"]), ("budget", _budget_words(training, shipped.get("step", 0))),
             ("steps done", str(shipped.get("step", "—")))]
    if training:
        runs = training.get("runs", [])
        lines += [("seed", str(training["seed"])),
                  ("learning rate", f"{training['lr']:g}, a cosine to 0 over the budget; {training['batch']} crops of "
                                    f"{training['crop']} px a step"),
                  ("started from", _file(training.get("init")) if training.get("init") else "random weights"),
                  ("teacher", f"{_file(training['teacher'])}, {training['teacher_weight']:g} of the loss"
                   if training.get("teacher") else "none"),
                  ("batch norm", "frozen at its running statistics" if training.get("freeze_norm") else "training"),
                  ("device", f"{training['device']}; threads: {training['threads']}; loaders: {training['loaders']}"),
                  ("training code", f"`{training['commit']}`"),
                  ("runs", ", ".join(f"steps {r['from_step']}-{r['to_step']}" for r in runs) +
                   (" (resumed: one uninterrupted run would draw other batches)" if len(runs) > 1 else ""))]
    lines.append(("exported at", f"`{shipped.get('commit', meta.get('commit', '—'))}`"))
    table = "\n".join(f"| {k} | {v} |" for k, v in lines)
    if not training:
        return f"""{table}

The checkpoint records no training configuration (it was trained before checkpoints recorded
one); nothing here says how to repeat it.
"""
    return f"""{table}

The same run again (the shard folder of the manifest above, on the same device kind and threads):
```bash
{reproduce_command(training, shipped['config'])}
```
"""


def _measured(figures: dict, machine: str) -> str:
    s, held, shipped = figures["summary"], figures["heldout"], figures.get("shipped") or {}
    real_rows = "\n".join(f"| `{r['stack']}` | {'x'.join(map(str, r['shape']))} | {_fmt(r['dice'])} | "
                          f"{r['ml']:.0f} | {r['confidence']:.2f} | {r['ms']:.0f} |" for r in figures["real"])
    scans = sorted({r["stack"].split("/")[0] for r in figures["real"] if r["dice"] is not None})
    real_dice = s["real_dice"]
    pr = figures["poses_real"] or {}
    what = {"brain": "the atlas's brain mask (the pose network's own definition)",
            "skull": "everything inside the skull (as manual masks are drawn)",
            "localiser": f"none: the localiser's, less its outer {POSE_MASK_INSET_MM:g} mm"}
    truth = figures.get("poses_truth") or {}
    truth_rows = "\n".join(f"| {what.get(k, k)} | {_fmt(v['median_ed_mm'], 2)} | {_fmt(v['mean_ed_mm'], 2)} | "
                           f"{_fmt(v['median_twin_min_mm'], 2)} | {_fmt(v['mean_twin_min_mm'], 2)} | {v['slices']} | "
                           f"{_fmt(100 * v['empty_share'], 0)} % |" for k, v in truth.items())
    real_table = ("| stack | size | Dice | volume (ml) | confidence | ms |\n|---|---|---|---|---|---|\n" + real_rows
                  if real_rows else "None: no real scan was found.")
    truth_table = ("| mask | median E.D. (mm) | mean E.D. | twin-min median | twin-min mean | brain slices posed | "
                   "left `empty` |\n|---|---|---|---|---|---|---|\n" + truth_rows if truth_rows else "None measured.")
    heldout = shipped.get("heldout")
    held_name = f"`{heldout['folder']}`, manifest sha256 `{heldout['manifest_sha256'][:16]}…`" if heldout else "—"
    ratios = [p["latency_ratio"] for p in figures["poses_heldout"]]
    volume_error = np.median([abs(r["ml"] - r["true_ml"]) / r["true_ml"] for r in held if r["true_ml"]] or [np.nan])
    return f"""
| set | stacks | Dice median | Dice min |
|---|---|---|---|
| generated whole-uterus validation ({held_name}) | {s['heldout_stacks']} | {_fmt(s['heldout_median_dice'])} | {_fmt(s['heldout_min_dice'])} |
| — of which T2-like contrast | {sum(1 for r in held if r.get('t2_like'))} | {_fmt(s.get('heldout_t2_like_median_dice'))} | |
| — of which every intensity drawn uniformly | {sum(1 for r in held if r.get('t2_like') is False)} | {_fmt(s.get('heldout_random_contrast_median_dice'))} | |
| real scans, manual masks ({', '.join(f'`{n}`' for n in scans) or 'none found'}) | {len(real_dice)} | {_fmt(float(np.median(real_dice)) if real_dice else None)} | {_fmt(min(real_dice) if real_dice else None)} |

Real stacks one by one (those without a manual mask: volume and confidence only):

{real_table}

Poses without masks against poses with the reference masks (`/v1/predict`'s pipeline, every stage on):

| set | median E.D. between the two (mm) | the same with masks twice (MC draws) | latency without / with masks |
|---|---|---|---|
| real scans, {len(real_dice)} stacks | {_fmt(pr.get('median_ed_mm'), 2)} | {_fmt(pr.get('repeat_median_ed_mm'), 2)} | {_fmt(pr.get('latency_ratio'), 2)} |
| generated validation stacks of T2-like contrast, one at a time ({len(figures['poses_heldout'])}) | {_fmt(s['poses_heldout_median_ed_mm'], 2)} | {_fmt(s.get('poses_heldout_repeat_median_ed_mm'), 2)} | {_fmt(float(np.median(ratios)) if ratios else None, 2)} |

Poses against the truth: held-out whole-uterus scenes whose slice poses are known (validation atlas
brains, T2-like contrast, each stack alone through the pipeline; `model_export/localiser/pose_accuracy.py`),
the brain slices of {s.get('pose_scenes', 0)} scenes' stacks:

{truth_table}

Localiser latency (320×320×22 stack, onnxruntime, {machine}): {s['latency_ms_320x320x22']:.0f} ms.
Generated validation stacks: median volume error {_fmt(float(volume_error) * 100, 1)} %.
"""


def write_card(path: Path, onnx_path: Path, figures: dict) -> Path:
    """Write ``card.md`` from the ONNX metadata and :func:`~model_export.localiser.evaluate.measure`'s
    figures with ``shipped`` (what ``ship`` records: the checkpoint's file record, its training
    record, steps done and shards, the held-out folder's identity, the commit, the machine)."""
    meta = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"]).get_modelmeta().custom_metadata_map
    shipped = figures.get("shipped") or {}
    s = figures["summary"]
    below = quick_look(budgets(figures))
    b = budgets(figures)
    banner = f"""
> **Quick look, not a model to use** ({', '.join(below)}).
> Trained {b['steps'] if b['steps'] is not None else 'an unrecorded number of'} steps (budget: {_budget_words(shipped.get('training'), b['steps'])}) on {b['shards'] if b['shards'] is not None else 'unrecorded'} generated stacks;
> measured on {b['heldout_stacks']} held-out stacks and {b['pose_scenes']} pose scenes.
> The figures below say what this run did, not what a trained localiser does.
""" if below else ""
    passes = {"run": "each slice and its mirror image, averaged", "learnt": "one (the network learnt the mirrored "
              "pass)"}.get(meta.get("mirrored_pass", "run"), meta.get("mirrored_pass"))
    arch_rows = "\n".join(f"| {a['inputs']} | {a['width']} | {a['depth']} | {_fmt(a['heldout_median_dice'])} | "
                          f"{_fmt(a['heldout_min_dice'])} | {_fmt(a['real_median_dice'])} | {a['ms']:.0f} |"
                          for a in figures.get("architectures") or [])
    architecture = f"""
## Architectures measured alike
`svrnet-train localiser compare` of checkpoints trained alike, given to `ship --ablation`:

| inputs | width | depth | held-out Dice median | min | real-scan Dice median | ms (320×320×22) |
|---|---|---|---|---|---|---|
{arch_rows}
""" if arch_rows else ""
    text = f"""# Brain localiser `{meta['version']}`
{banner}
{meta['architecture']} on a {meta['grid_mm']} mm grid; {s['onnx_mb']:.1f} MB ONNX; passes: {passes}.
It finds the fetal brain (everything inside the skull: brain and
extra-axial CSF) in stacks as they leave the scanner, whole uterus and maternal body included: what
the service runs for a stack sent without a mask once this folder is its localisers' `default`
(`SVRNET_LOCALISERS_DIR/default`; under another name `/v1/masks` runs it when a request names it).

## Intended use
Research use only (the atlas licences below): fetal brain T2-weighted single-shot stacks, any
orientation, any in-plane pixel size and field of view. Not for clinical decisions. The answer's
`confidence` is low when no brain-like region is found; check it, or upload masks.

## Training data
Synthetic whole-uterus stacks only (`model_export/localiser/scenes.py`, described in
docs/localisation.md): atlas brains (the volumes named in the settings below) put into generated
surroundings. No real scan was used for training or tuning.

{_training_data(shipped)}
Licences of the data: {meta['licences']}. The model inherits the most restrictive: non-commercial research use.

## How it was made

| | |
|---|---|
{_made(shipped, meta)}
## Measured
{_measured(figures, shipped.get('machine', 'the shipping machine'))}{architecture}
## Limits
- Trained on synthetic surroundings: organs and textures unlike those generated may be taken for brain;
  the geometry step keeps one connected brain of plausible volume and reports its confidence.
- Stacks covering only part of the head give a partial mask (what the stack shows).
- The mask is the skull's inside, as manual masks are drawn. The service cuts the pose network's
  slices with the localiser's mask less its outer {POSE_MASK_INSET_MM:g} mm (`POSE_MASK_INSET_MM`).
- Gestational ages and malformations beyond the atlas volumes it was trained on are untested.
"""
    Path(path).write_text(text)
    return Path(path)
