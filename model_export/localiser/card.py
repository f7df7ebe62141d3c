"""The localiser's model card: what it is, what it was trained on, under which licences, how well it does."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort


def _fmt(x: float | None, digits: int = 3) -> str:
    return "—" if x is None else f"{x:.{digits}f}"


def write_card(path: Path, onnx_path: Path, figures: dict) -> Path:
    """Write ``card.md`` from the ONNX metadata and :func:`~model_export.localiser.evaluate.measure`'s figures."""
    meta = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"]).get_modelmeta().custom_metadata_map
    s = figures["summary"]
    held = figures["heldout"]
    real_rows = "\n".join(f"| `{r['stack']}` | {'x'.join(map(str, r['shape']))} | {_fmt(r['dice'])} | "
                          f"{r['ml']:.0f} | {r['confidence']:.2f} | {r['ms']:.0f} |" for r in figures["real"])
    pr = figures["poses_real"] or {}
    arch_rows = "\n".join(f"| {a['inputs']} | {a['width']} | {a['depth']} | {_fmt(a['heldout_median_dice'])} | "
                          f"{_fmt(a['heldout_min_dice'])} | {_fmt(a['real_median_dice'])} | {a['ms']:.0f} |"
                          for a in figures.get("architectures") or [])
    architecture = f"""
## Architecture, chosen by measurement
The same data, seed and wall-clock budget for each (10 minutes, trained side by side on one core
each, from scratch; `svrnet-train localiser compare`). At this budget the two are within each other's
noise; the 2.5D network is kept for its better worst case and real-scan Dice at no extra cost (only
its first convolution differs).

| inputs | width | depth | held-out Dice median | min | real-scan Dice median | ms (320×320×22) |
|---|---|---|---|---|---|---|
{arch_rows}
""" if arch_rows else ""
    text = f"""# Brain localiser `{meta['version']}`

{meta['architecture']} on a {meta['grid_mm']} mm grid; {s['onnx_mb']:.1f} MB ONNX. It finds the fetal brain
(everything inside the skull: brain and extra-axial CSF) in stacks as they leave the scanner, whole uterus
and maternal body included, and is what the service runs for every stack sent without a mask
(`/v1/predict`, `/v1/masks`, reconstruction jobs).

## Intended use
Research use only (the CRL atlas's licence): fetal brain T2-weighted single-shot stacks of 20–40 weeks'
gestation, any orientation, any in-plane pixel size and field of view. Not for clinical decisions. The
answer's `confidence` is low when no brain-like region is found; check it, or upload masks.

## Training data
Synthetic stacks only (`model_export/localiser/scenes.py`, style `train`): the 18 training atlas brains of
`model_export.atlas.split` (CRL spatio-temporal atlas, Gholipour et al. 2017; fetal spina-bifida atlas,
Fidon et al. 2021) put, in any orientation and with slice-to-slice motion, into generated surroundings:
extra-axial CSF, skull, scalp; amniotic fluid, uterine wall, placenta, fetal body and limbs; the mother's
tissues, fat and the air around her; random intensities, bias fields, slice profiles of 2–4.5 mm,
0.9–1.6 mm pixels, 250–400 mm fields of view, Rician noise. No real scan was used for training or tuning.

Licences of the data: {meta['licences']}. The model inherits the most restrictive: non-commercial research use.

## How it was made
```bash
svrnet-train localiser data --out T --count 600            # seeds 0-599 (and --seed 10000, 20000, 30000 as the generator grew)
svrnet-train localiser train --data T --out L.pt --minutes 60   # 2 CPU cores, cosine over the budget; resumable
svrnet-train localiser data --out H --count 40 --style heldout --seed 1000000 --keep-stack
svrnet-train localiser ship L.pt --heldout H --ablation A.json  # this card and evaluation.json
```
`checkpoint.pt` beside this card is the shipped network's training state: `svrnet-train localiser train
--out` a copy of it resumes training from there.

## Measured

| set | stacks | Dice median | Dice min |
|---|---|---|---|
| generated whole-uterus validation (validation atlas volumes; held-out surroundings generator) | {s['heldout_stacks']} | {_fmt(s['heldout_median_dice'])} | {_fmt(s['heldout_min_dice'])} |
| — of which T2-like contrast | {sum(1 for r in held if r.get('t2_like'))} | {_fmt(s.get('heldout_t2_like_median_dice'))} | |
| — of which every intensity drawn uniformly | {sum(1 for r in held if r.get('t2_like') is False)} | {_fmt(s.get('heldout_random_contrast_median_dice'))} | |
| real scan, manual masks (`mial_lausanne_t30`) | {len(s['real_dice'])} | {_fmt(float(np.median(s['real_dice'])) if s['real_dice'] else None)} | {_fmt(min(s['real_dice']) if s['real_dice'] else None)} |

Real stacks one by one (the BCH stacks have no manual mask: volume and confidence only):

| stack | size | Dice | volume (ml) | confidence | ms |
|---|---|---|---|---|---|
{real_rows}

Poses without masks against poses with the reference masks (`/v1/predict`'s pipeline, every stage on):

| set | median E.D. between the two (mm) | the same with masks twice (MC draws) | latency without / with masks |
|---|---|---|---|
| real scan, 3 stacks | {_fmt(pr.get('median_ed_mm'), 2)} | {_fmt(pr.get('repeat_median_ed_mm'), 2)} | {_fmt(pr.get('latency_ratio'), 2)} |
| generated validation stacks of T2-like contrast, one at a time ({len(figures['poses_heldout'])}) | {_fmt(s['poses_heldout_median_ed_mm'], 2)} | {_fmt(s.get('poses_heldout_repeat_median_ed_mm'), 2)} | {_fmt(float(np.median([p['latency_ratio'] for p in figures['poses_heldout']])) if figures['poses_heldout'] else None, 2)} |

Localiser latency (320×320×22 stack, this machine's 2 CPU cores, onnxruntime): {s['latency_ms_320x320x22']:.0f} ms.
Generated validation stacks: median volume error {np.median([abs(r['ml'] - r['true_ml']) / r['true_ml'] for r in held]) * 100:.1f} %.

{architecture}
## Limits
- Trained on synthetic surroundings: organs and textures unlike those generated may be taken for brain;
  the geometry step keeps one connected brain of plausible volume and reports its confidence.
- Stacks covering only part of the head give a partial mask (what the stack shows).
- The outermost slices of a head, where the cut shows mostly CSF and ventricles, are the ones most
  often missed (the real sagittal stack above loses them: Dice 0.76).
- Poses without masks differ from those with manual masks by more than two runs with the same masks
  differ (MC draws): the masks' extent changes what the pose network sees. On single generated stacks
  a few differ by the left-right twin (tens of mm): a single stack that cannot settle its branch.
- Gestational ages outside 21–38 weeks and severe malformations beyond the spina-bifida atlas are untested.
"""
    Path(path).write_text(text)
    return Path(path)
