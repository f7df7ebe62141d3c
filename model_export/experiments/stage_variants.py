"""The stages after the network, in variants, on the same cached network outputs: exact comparisons.

Another ensemble of MC draws moves a request's figures by tenths of a millimetre, as much as most
changes of the stages do. So this script runs the network once per simulated acquisition
(every held-out volume, ``--per-volume`` acquisitions per motion level, ``--seed``), keeps the
prepared stacks and the network's estimates in ``--cache``, and sends the same estimates through
``/v1/predict``'s stages (:func:`~service.pipeline.predict.predict_from_estimates`) once per
variant. A variant is ``base`` or a ``;``-separated list of overrides:

* ``consistency.stack_fit.OUTLIER_K=2.0``: a module constant under ``service.`` (a Python literal);
* ``refine:passes=((3.0, 3.0, None), (0.9, 2.0, None))``: a keyword of the image refinement
  (:func:`~service.consistency.image_refinement.refine`).

``--columns OUT.npz`` writes every cached slice's columns for ``svrnet-train calibrate-acceptance
--columns`` (a second set of acquisitions pooled with the first).
``--void`` puts a dark ball in every acquisition (:func:`~model_export.experiments.scanner_sweep.with_void`);
``--signal-loss`` a signal loss over the brain in a run of each stack's slices
(:func:`~model_export.experiments.scanner_sweep.with_signal_loss`);
``--last-to-first`` stores every stack with its slices the other way (the same acquisitions);
``--alone`` sends each stack as a request of its own (a single-stack request, or a stream's first stack).
``--source VOLUME`` (repeatable) simulates from these volumes instead of the held-out atlas brains: a
job's reconstruction of a real scan (atlas space; its brain from its own intensities,
:func:`~model_export.experiments.real_brain_acquisitions.source_volumes`), a real brain's texture where
the atlases are population averages (docs/reports/accuracy-analyses.md).
Per motion level it prints the mean E.D. against the truth and twin-min, the median E.D. once the
acquisition's common rigid offset is undone (what the images can tell: "frame-free"), the share of
slices under 5 mm and over 10 mm accepted (and how many are over 10 mm), RMS E.D. over RMS
``expected_error_mm``, and the variant's time.
Slices with at least 20 mask pixels count, as in the evaluation. A cache made again with a model of
fixed draws holds the same draws; made with a model of another seed (or one that draws in its
graph) its figures differ by tenths of a millimetre; the variants within one cache are compared
exactly. The cached outputs are judged with ``--model``'s calibration as it is
now (its accept flags, expected-error calibration), not the one they were cached with.

    .venv/bin/python model_export/experiments/stage_variants.py --cache /tmp/stages-21.pkl --seed 21 \\
        base "refine:passes=((3.0, 3.0, None), (0.9, 2.0, None))"                  # needs ../shared/data
"""

from __future__ import annotations

import argparse
import functools
import importlib
import pickle
import sys
import time
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.acquisitions import MOTION_LEVELS, simulate_acquisition, stored_last_to_first  # noqa: E402
from model_export.atlas import DEFAULT_ATLAS_ROOT, held_out_volumes  # noqa: E402
from model_export.calibrate_acceptance import measuring, rates, rms, share  # noqa: E402
from model_export.evaluate_acquisitions import MIN_MASK_PIXELS, acceptance_columns, prepare_acquisition  # noqa: E402
from model_export.experiments.frame_bias import common_frame  # noqa: E402
from model_export.experiments.real_brain_acquisitions import source_volumes  # noqa: E402
from model_export.experiments.scanner_sweep import with_signal_loss, with_void  # noqa: E402
from model_export.packaging import CALIBRATION  # noqa: E402
from service.geometry import twin  # noqa: E402
from service.geometry.anchors import ed  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator  # noqa: E402
from service.inference.model_file import ModelInfo, load_model  # noqa: E402
import service.pipeline.predict as pipeline  # noqa: E402
from service.pipeline import image_stage  # noqa: E402


def build(model: Path, root: Path, levels: list[str], per_volume: int, seed: int, void: bool = False,
          sources: list[Path] | None = None, last_to_first: bool = False, signal_loss: bool = False) -> tuple:
    """``(info, [(level, prepared stacks, estimates per stack, true poses per stack), ...])``; from
    ``sources`` (:func:`~model_export.experiments.real_brain_acquisitions.source_volumes`) where given, else from the held-out atlas brains;
    with ``last_to_first`` each stack stored with its slices the other way
    (:func:`~model_export.acquisitions.stored_last_to_first`)."""
    loaded = load_model(model)
    estimator = OnnxPoseEstimator(loaded)
    volumes = source_volumes(sources) if sources else held_out_volumes(loaded.info.metadata, root)
    rng = np.random.default_rng(seed)
    cases = []
    for level in levels:
        for vol in volumes * per_volume:
            stacks = simulate_acquisition(vol.image, vol.mask, vol.affine, rng, level)
            stacks = [stored_last_to_first(s) for s in stacks] if last_to_first else stacks
            stacks = with_void(stacks, rng) if void else stacks
            stacks = with_signal_loss(stacks, rng) if signal_loss else stacks
            prepared, truth = prepare_acquisition(stacks, loaded.info)
            parts, _ = pipeline.estimate_stacks(prepared, estimator, 100)
            cases.append((level, prepared, parts, truth))
    return loaded.info, cases


def calibrated_as(info: ModelInfo, model: ModelInfo) -> ModelInfo:
    """``info`` (a cache's) with ``model``'s calibration (:data:`~model_export.packaging.CALIBRATION`;
    a cache keeps the network's outputs, not its calibration): the cached network outputs judged as
    the model judges them now."""
    return replace(info, **{k: getattr(model, k) for k in CALIBRATION})


def overridden(variant: str) -> list[tuple[object, str, object]]:
    """Apply ``variant``'s overrides; returns what to put back."""
    saved: list[tuple[object, str, object]] = []
    if variant == "base":
        return saved
    for item in variant.split(";"):
        name, value = (s.strip() for s in item.split("=", 1))
        if name.startswith("refine:"):
            saved.append((image_stage, "refine", image_stage.refine))
            image_stage.refine = functools.partial(image_stage.refine, **{name[len("refine:"):]: eval(value)})  # noqa: S307
            continue
        module, constant = name.rsplit(".", 1)
        target = importlib.import_module(f"service.{module}")
        saved.append((target, constant, getattr(target, constant)))
        setattr(target, constant, eval(value))                                                     # noqa: S307
    return saved


def frame_free(poses: np.ndarray, truth: np.ndarray, plane: float) -> np.ndarray:
    """E.D. of each pose from the nearer of its truth and twin once the acquisition's common error
    (:func:`~model_export.experiments.frame_bias.common_frame`, about the slices' centre) is undone."""
    near = twin.nearer(poses, truth, plane)
    return common_frame(poses, near, near[:, :3, 3].mean(axis=0))[1]


def requests(prepared: list, parts: list, alone: bool) -> list[tuple[list, list]]:
    """The acquisition as one request, or (``alone``) each stack as a request of its own."""
    return [([p], [e]) for p, e in zip(prepared, parts)] if alone else [(prepared, parts)]


def run(info, cases: list, variant: str, alone: bool = False, by_signal: bool = False) -> str:  # noqa: ANN001
    """One variant over every cached acquisition (``alone``: each stack sent on its own): a line per
    motion level (``by_signal``: and one each for the slices that lost their signal and the others)."""
    saved = overridden(variant)
    columns: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    start = time.perf_counter()
    try:
        for level, prepared, parts, truth in cases:
            predictions = [p for request in requests(prepared, parts, alone)
                           for p in pipeline.predict_from_estimates(*request, info, info.variance_threshold)[0]]
            keep = [p.prepared.prepared.mask_pixels >= MIN_MASK_PIXELS for p in predictions]
            poses = np.concatenate([p.poses.poses[k] for p, k in zip(predictions, keep)])
            true = np.concatenate([t[k] for t, k in zip(truth, keep)])
            col = columns[level]
            col["ed"].append(ed(poses, true))
            col["twin_min"].append(twin.twin_min_ed(poses, true, info.symmetry_plane_x_mm))
            col["frame_free"].append(frame_free(poses, true, info.symmetry_plane_x_mm))
            col["accepted"].append(np.concatenate([np.array([r is None for r in p.reasons])[k]
                                                   for p, k in zip(predictions, keep)]))
            col["expected"].append(np.concatenate([np.full(k.sum(), np.nan) if p.poses.expected_error_mm is None
                                                   else p.poses.expected_error_mm[k] for p, k in zip(predictions, keep)]))
            col["lost"].append(np.concatenate([p.prepared.signal_lost[k] for p, k in zip(predictions, keep)]))
    finally:
        for target, name, value in saved:
            setattr(target, name, value)
    lines = [f"{variant}  ({time.perf_counter() - start:.0f} s)"]
    for level, col in columns.items():
        lost = np.concatenate(col["lost"])
        groups = {"": np.ones(len(lost), bool)}
        if by_signal:
            groups.update({"  signal lost": lost, "  the others": ~lost})
        for label, rows in groups.items():
            e, t, f, a, x = (np.concatenate(col[k])[rows] for k in ("ed", "twin_min", "frame_free", "accepted", "expected"))
            if not len(e):
                continue
            shares, known = rates({"ed": e, "ed_min": t}, a), np.isfinite(x)
            ratio = rms(e[known]) / rms(x[known]) if known.any() else np.nan
            lines.append(f"  {level + label:24s} E.D. {e.mean():.2f} / twin-min {t.mean():.2f} mm, frame-free median "
                         f"{np.median(f):.2f} mm; accepted: {share(shares['good_accepted'])} of < 5 mm, "
                         f"{share(shares['bad_accepted'])} of > 10 mm ({shares['bad_slices']} slices, {len(e)} in all);"
                         f" RMS E.D. / RMS expected {ratio:.2f}")
    return "\n".join(lines)


def write_columns(info: ModelInfo, cases: list, path: Path) -> None:
    """Every cached slice's columns as :func:`~model_export.calibrate_acceptance.level_columns` reads
    them (``<level>/<column>``), the calibration switched off as ``calibrate-acceptance`` measures
    (no floor, limit or twin risk): a second set of acquisitions for ``calibrate-acceptance
    --columns A.npz --columns B.npz``."""
    measured = measuring(info)
    columns: dict[str, list] = defaultdict(list)
    for level, prepared, parts, truth in cases:
        for p, true in zip(pipeline.predict_from_estimates(prepared, parts, measured, measured.variance_threshold)[0],
                           truth):
            expected = p.poses.expected_error_mm
            found = acceptance_columns(p.poses.poses, true, [None] * len(true) if expected is None else expected,
                                       p.estimate.variance, p.reasons, p.prepared.prepared.mask_pixels,
                                       p.poses.fit is not None and p.poses.fit.decidable, info.symmetry_plane_x_mm)
            for key, value in found.items():
                columns[f"{level}/{key}"].append(value)
    np.savez_compressed(path, **{k: np.concatenate(v) for k, v in columns.items()})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("variants", nargs="*", default=["base"])
    ap.add_argument("--cache", type=Path, required=True, help="the network's outputs (a pickle; made when absent)")
    ap.add_argument("--model", type=Path, default=Path("service/models/default/model.onnx"))
    ap.add_argument("--root", type=Path, default=DEFAULT_ATLAS_ROOT)
    ap.add_argument("--levels", default="mild,moderate,jumps,independent",
                    help=f"of {', '.join(MOTION_LEVELS)} (extreme motion leaves every stack undecidable: the stages change nothing)")
    ap.add_argument("--per-volume", type=int, default=2)
    ap.add_argument("--seed", type=int, default=21)
    ap.add_argument("--void", action="store_true", help="a dark ball in every acquisition (scanner_sweep.with_void)")
    ap.add_argument("--signal-loss", action="store_true",
                    help="a signal loss over the brain in a run of slices of every stack (scanner_sweep.with_signal_loss)")
    ap.add_argument("--last-to-first", action="store_true",
                    help="each stack stored with its slices the other way (the same draws): its interleaved order runs downwards")
    ap.add_argument("--alone", action="store_true", help="each stack sent on its own, not with its acquisition's others")
    ap.add_argument("--by-signal", action="store_true",
                    help="also a line each for the slices that lost their signal and for the others")
    ap.add_argument("--columns", type=Path, help="write every slice's columns here (.npz) for calibrate-acceptance --columns")
    ap.add_argument("--source", type=Path, action="append", default=[],
                    help="simulate from this volume (atlas space: a job's reconstruction) instead of the atlas brains")
    args = ap.parse_args()
    if not args.cache.exists():             # written whole or not at all: a stopped build leaves no cache
        built = build(args.model, args.root, args.levels.split(","), args.per_volume, args.seed, args.void, args.source,
                      args.last_to_first, args.signal_loss)
        partial = args.cache.with_name(args.cache.name + ".partial")
        with open(partial, "wb") as f:
            pickle.dump(built, f)
        partial.replace(args.cache)
    with open(args.cache, "rb") as f:
        info, cases = pickle.load(f)                                                               # noqa: S301 - our own file
    info = calibrated_as(info, load_model(args.model).info)
    if args.columns:
        write_columns(info, cases, args.columns)
    for variant in args.variants:
        print(run(info, cases, variant, args.alone, args.by_signal), flush=True)


if __name__ == "__main__":
    main()
