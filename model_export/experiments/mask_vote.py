"""A real scan's poses without masks, some of their slices kept out of every stage, against the
poses with its manual masks: does leaving out the slices whose localiser mask is poor bring the two
answers together?

The localiser's masks are worst at the ends of a stack's brain (the skull base and the face, the
poles): on the nine masked real stacks at hand, 30 of the 35 slices whose mask scores a Dice under
0.8 against the manual one lie within two slices of an end of the brain the localiser found. Those
slices' network poses move most with the mask, and at the end of a stack they have the most leverage
on its rigid fit. Each variant marks some slices of the no-mask answer as degenerate after the
network (:attr:`~service.inference.estimator.PoseEstimate.degenerate`: no stage uses them, none is
accepted) and compares the answer with the manual masks' one (sent with ``masks_hold_csf``), both
with the model's fixed draws of seed + 0, 1, ... (``--repeats``):

* ``none``: the no-mask answer as the service gives it;
* ``dice<D``: an oracle, the slices whose localiser mask scores a Dice under ``D`` against the manual
  mask of the same slice;
* ``ends:E``: no oracle, the ``E`` outermost slices at each end of the localiser's brain;
* ``soft-ends:E:F``: those slices kept, their expected errors (the MC spread the stages weigh them
  by) ``F`` times larger;
* ``unsure:T:F``: no oracle, the slices whose mean localiser probability inside their mask is under
  ``T`` kept, their expected errors ``F`` times larger;
* ``graded:T:F``: no oracle, every slice's expected error grown in proportion to how far that mean
  probability lies under ``T``: by 1 at ``T`` and up to ``F`` times at 0.5, the mask's own cut.

Per variant and repeat: the slices both answers accept, their median E.D. (per stack too), the
common rigid offset of the no-mask answer against the manual one (about the brain's centre,
:func:`~model_export.experiments.frame_bias.common_frame`) and the median E.D. once it is undone.

With ``--scenes N`` the variants without an oracle run instead on ``N`` generated whole-uterus scenes
without masks, against their truth (:mod:`model_export.localiser.pose_accuracy`).

    .venv/bin/python model_export/experiments/mask_vote.py [SCAN_FOLDER] [--variants none,dice<0.8,ends:2] [--repeats 2]
    .venv/bin/python model_export/experiments/mask_vote.py --scenes 10 --variants none,ends:2
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.experiments.frame_bias import common_frame  # noqa: E402
from model_export.experiments import real_scan_poses  # noqa: E402
from model_export.localiser.evaluate import REAL_SCANS, dice  # noqa: E402
from model_export.localiser.pose_accuracy import pose_estimator  # noqa: E402
from model_export.localiser.pose_accuracy import pose_accuracy, slice_poses, validation_scenes  # noqa: E402
from service.geometry import anchors, se3  # noqa: E402
from service.inference import acceptance  # noqa: E402
from service.inference.acceptance import ATLAS_CENTRE_MM  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator, PoseEstimator  # noqa: E402
from service.io.volume import Volume  # noqa: E402
from service.pipeline import predict as pipeline  # noqa: E402
from service.pipeline.prepare import PreparedStack  # noqa: E402
from service.preprocess.localise import default_localiser  # noqa: E402


def mean_inside(prepared: PreparedStack) -> NDArray[np.float64]:
    """Each slice's mean localiser probability inside its localiser mask (NaN: no mask there)."""
    axis = prepared.upload.slice_axis
    probability, grid = default_localiser().probabilities(prepared.upload.volume)
    found = np.moveaxis(prepared.localisation.mask, axis, -1)
    inside = np.moveaxis(grid.to_stack(probability), axis, -1)
    return np.array([inside[..., k][found[..., k]].mean() if found[..., k].any() else np.nan
                     for k in range(found.shape[-1])])


def spread_factor(variant: str, prepared: PreparedStack) -> NDArray[np.float64]:
    """``graded:T:F``: each slice's factor on its expected error (see the module)."""
    _, top, most = variant.split(":")
    under = np.clip((float(top) - mean_inside(prepared)) / (float(top) - 0.5), 0.0, 1.0)
    return 1.0 + (float(most) - 1.0) * np.nan_to_num(under)


def kept_out(variant: str, prepared: PreparedStack, manual: Volume | None) -> NDArray[np.bool_]:
    """The slices of a no-mask ``prepared`` stack that ``variant`` keeps out (see the module)."""
    brain = prepared.prepared.mask_fraction >= acceptance.MIN_MASK_FRACTION
    out = np.zeros(len(brain), bool)
    if variant.startswith("dice<"):
        axis = prepared.upload.slice_axis
        found, truth = np.moveaxis(prepared.localisation.mask, axis, -1), np.moveaxis(manual.array > 0, axis, -1)
        for k in range(len(out)):
            if found[..., k].any() or truth[..., k].any():
                out[k] = dice(found[..., k], truth[..., k]) < float(variant[5:])
    elif variant.startswith(("ends:", "soft-ends:")):
        ends, slices = int(variant.split(":")[1]), np.flatnonzero(brain)
        out[slices[:ends]] = out[slices[len(slices) - ends:]] = True
    elif variant.startswith("unsure:"):
        out = brain & (np.nan_to_num(mean_inside(prepared), nan=1.0) < float(variant.split(":")[1]))
    elif variant != "none":
        raise ValueError(f"unknown variant {variant!r}")
    return out


@contextmanager
def keeping_out(variant: str, manual: dict[str, Volume] | None = None) -> Iterator[None]:
    """Within the block, every stack that ``/v1/predict``'s pipeline localised has the slices
    ``variant`` names kept out (marked degenerate after the network); ``manual``: the manual masks by
    upload name (for ``dice<D``)."""
    original = pipeline.estimate_stacks

    def estimate(prepared: list[PreparedStack], estimator: PoseEstimator, mc_samples: int):  # noqa: ANN202
        parts, timings = original(prepared, estimator, mc_samples)
        for part, p in zip(parts, prepared):
            if p.localisation.method == "network":
                if variant.startswith("graded:"):
                    part.spread_mm = part.spread_mm * spread_factor(variant, p)
                    continue
                out = kept_out(variant, p, (manual or {}).get(p.upload.filename))
                if variant.startswith(("soft-ends:", "unsure:")):  # trusted less, not left out
                    part.spread_mm = np.where(out, part.spread_mm * float(variant.split(":")[2]), part.spread_mm)
                else:
                    part.degenerate = part.degenerate | out
        return parts, timings

    pipeline.estimate_stacks = estimate
    try:
        yield
    finally:
        pipeline.estimate_stacks = original


def answer(volumes: dict[str, Volume], manual: dict[str, Volume], estimator: PoseEstimator,
           variant: str | None) -> tuple[list[dict], list[PreparedStack]]:
    """``/v1/predict``'s stacks with the manual masks (``variant`` None), or without masks and the
    slices ``variant`` names kept out (:func:`~model_export.experiments.real_scan_poses.answer`)."""
    with keeping_out(variant or "none", manual):
        return real_scan_poses.answer(volumes, None if variant else manual, default_localiser(), estimator)


def accepted_in_both(first: list[dict], second: list[dict], prepared: list[PreparedStack]) -> list[tuple[NDArray, NDArray]]:
    """Per stack, the two answers' slice poses (in ``prepared``'s slice frames,
    :func:`~model_export.localiser.pose_accuracy.slice_poses`) over the slices both pose and accept."""
    pairs = []
    for sa, sb, p in zip(first, second, prepared):
        (xa, ka), (xb, kb) = slice_poses(sa, p), slice_poses(sb, p)
        both = ka & kb & np.array([x["accepted"] and y["accepted"] for x, y in zip(sa["slices"], sb["slices"])])
        pairs.append((xa[both], xb[both]))
    return pairs


def common_offset(pairs: list[tuple[NDArray, NDArray]]) -> tuple[NDArray, NDArray, NDArray, NDArray] | None:
    """The pairs of :func:`accepted_in_both` joined over the stacks (the first answer's poses, the
    second's), their common rigid offset about the atlas centre and what is left per slice once it
    is undone (:func:`~model_export.experiments.frame_bias.common_frame`); None without a pair."""
    a, b = np.concatenate([x for x, _ in pairs]), np.concatenate([y for _, y in pairs])
    if not len(a):
        return None
    frame, left = common_frame(b, a, ATLAS_CENTRE_MM)
    return a, b, frame, left


def agreement(with_masks: list[dict], without: list[dict], prepared: list[PreparedStack]) -> str:
    """The two answers' distance over the slices both accept (see the module), as a line."""
    pairs = accepted_in_both(with_masks, without, prepared)
    joined = common_offset(pairs)
    if joined is None:
        return "no slice accepted in both"
    a, b, frame, left = joined
    per_stack = ", ".join(f"{np.median(anchors.ed(x, y)):.1f}" if len(x) else "-" for x, y in pairs)
    return (f"{len(a)} slices, median {np.median(anchors.ed(a, b)):.2f} mm (per stack {per_stack}); common "
            f"{np.linalg.norm(frame[:3, 3]):.2f} mm / {np.degrees(np.linalg.norm(se3.so3_log(frame[:3, :3]))):.2f} deg; "
            f"undone {np.median(left):.2f} mm")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scan", type=Path, nargs="?", default=REAL_SCANS / "mial_lausanne_t30")
    ap.add_argument("--variants", default="none,dice<0.8,ends:2,ends:3")
    ap.add_argument("--repeats", type=int, default=2, help="pairs of answers, with the model's draws of seed + 0, 1, ...")
    ap.add_argument("--scenes", type=int, default=0,
                    help="instead: this many generated whole-uterus scenes without masks against the truth "
                         "(model_export.localiser.pose_accuracy), per variant without an oracle")
    args = ap.parse_args()
    base = pose_estimator(None)
    if args.scenes:
        scenes = validation_scenes(args.scenes)
        for variant in [v for v in args.variants.split(",") if not v.startswith("dice<")]:
            with keeping_out(variant):
                got = pose_accuracy(scenes, base, default_localiser(), ("localiser",))["localiser"]
            print(f"{variant}: {json.dumps({k: round(v, 2) for k, v in got.items()})}", flush=True)
        return
    volumes, manual = real_scan_poses.read_scan(args.scan)
    for r in range(args.repeats):
        estimator = (base if r == 0 or base.model.mc_seed is None
                     else OnnxPoseEstimator(base.model.with_seed(base.model.mc_seed + r)))
        with_masks, prepared = answer(volumes, manual, estimator, None)
        for variant in args.variants.split(","):
            without, _ = answer(volumes, manual, estimator, variant)
            print(f"seed + {r}, {variant}: {agreement(with_masks, without, prepared)}", flush=True)


if __name__ == "__main__":
    main()
