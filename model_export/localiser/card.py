"""The localiser's model card: what it is, what it was trained on, under which licences, how well it does."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort

from service.preprocess.localisation import POSE_MASK_INSET_MM


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
    what = {"brain": "the atlas's brain mask (the pose network's own definition)",
            "skull": "everything inside the skull (as manual masks are drawn)",
            "localiser": f"none: the localiser's, less its outer {POSE_MASK_INSET_MM:g} mm"}
    truth = figures.get("poses_truth") or {}
    truth_rows = "\n".join(f"| {what.get(k, k)} | {_fmt(v['median_ed_mm'], 2)} | {_fmt(v['mean_ed_mm'], 2)} | "
                           f"{_fmt(v['median_twin_min_mm'], 2)} | {_fmt(v['mean_twin_min_mm'], 2)} | {v['slices']} | "
                           f"{_fmt(100 * v['empty_share'], 0)} % |" for k, v in truth.items())
    truth_scenes = s.get("pose_scenes", 10)
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
Synthetic stacks only (`model_export/localiser/scenes.py`, style `train`): every atlas brain but the five
validation volumes (`model_export.atlas.training_volumes`; CRL spatio-temporal atlas, Gholipour et al.
2017; fetal spina-bifida atlas, Fidon et al. 2021) put, in any orientation and with slice-to-slice motion,
into generated surroundings:
extra-axial CSF, skull, scalp; amniotic fluid, uterine wall, placenta, fetal body and limbs; the mother's
tissues, fat and the air around her; for 30 % of the stacks the head at or beyond the uterine wall (low in
the maternal pelvis, no fluid around it), for 25 % in tissue as bright and as textured as the brain behind
a thin CSF layer and skull; random intensities, bias fields and surface-coil fall-off,
odd and even slices of different gain, slice profiles of 2–4.5 mm, 0.9–1.6 mm pixels, 130–400 mm fields
of view, Rician noise. Each training sample's contrast changes again (a global scale, gamma, a smooth
field, neighbours brighter or darker than the slice). No real scan was used for training or tuning.

Licences of the data: {meta['licences']}. The model inherits the most restrictive: non-commercial research use.

## How it was made
```bash
svrnet-train localiser data --out T0 --count 600            # 1.0.0: seeds 0-599 (and 10000, 20000, 30000 as the generator grew)
svrnet-train localiser train --data T0 --out L1.pt --minutes 60 # 2 CPU cores, cosine over the budget; resumable
svrnet-train localiser data --out T --count 505 --seed 40000    # 1.1.0: the generator with engaged heads and slice gains
svrnet-train localiser train --data T --out L2.pt --minutes 60 --init L1.pt --lr 1e-3   # fine-tuned, fresh schedule
svrnet-train localiser average L1.pt L2.pt --out L11.pt --weight 0.5 # half each: weight-space ensembling (WiSE-FT)
svrnet-train localiser data --out T3 --count 500 --seed 60000   # 1.2.0: the generator with camouflaged heads; T3 also holds T
svrnet-train localiser train --data T3 --out L3.pt --minutes 75 --init L11.pt --lr 1e-3 --seed 3
svrnet-train localiser train --data T3 --out L4.pt --minutes 40 --init L3.pt --lr 5e-4 --seed 4  # a second round
svrnet-train localiser data --out H --count 40 --style heldout --seed 1000000 --keep-stack
svrnet-train localiser ship L4.pt --heldout H --ablation A.json --version 1.2.0  # this card and evaluation.json
```
1.2.0 is the fine-tuned network itself: on the held-out set (which has camouflaged heads too) the first
round did better than its average with 1.1.0 (weights 0.5 and 0.75), whose only gain was on one real
stack, and the second round better than the first (mean Dice 0.950 against 0.946, minimum 0.740 against 0.709).
`checkpoint.pt` beside this card holds the shipped network's weights: `svrnet-train localiser train --init
checkpoint.pt` fine-tunes from them with a fresh schedule.

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

Poses against the truth: held-out whole-uterus scenes whose slice poses are known (validation atlas
brains, T2-like contrast, each stack alone through the pipeline; `model_export/localiser/pose_accuracy.py`),
the brain slices of {truth_scenes} scenes' stacks:

| mask | median E.D. (mm) | mean E.D. | twin-min median | twin-min mean | brain slices posed | left `empty` |
|---|---|---|---|---|---|---|
{truth_rows}

Localiser latency (320×320×22 stack, this machine's 2 CPU cores, onnxruntime): {s['latency_ms_320x320x22']:.0f} ms.
Generated validation stacks: median volume error {np.median([abs(r['ml'] - r['true_ml']) / r['true_ml'] for r in held]) * 100:.1f} %.

{architecture}
## Limits
- Trained on synthetic surroundings: organs and textures unlike those generated may be taken for brain;
  the geometry step keeps one connected brain of plausible volume and reports its confidence.
- Stacks covering only part of the head give a partial mask (what the stack shows).
- A head deep in the maternal pelvis, without fluid around it and darker than the rest of the field of
  view, is the hardest case seen; the real stacks above show how much of it is found.
- The mask is the skull's inside, as manual masks are drawn. The pose network learnt the atlas's brain
  masks, which leave out most extra-axial CSF: the service cuts the pose network's slices with the
  localiser's mask less its outer {POSE_MASK_INSET_MM:g} mm (`POSE_MASK_INSET_MM`). An uploaded mask is used as it is; one
  that holds the CSF rim gives worse poses (the table above).
- Gestational ages outside 21–38 weeks and severe malformations beyond the spina-bifida atlas are untested.
"""
    Path(path).write_text(text)
    return Path(path)
