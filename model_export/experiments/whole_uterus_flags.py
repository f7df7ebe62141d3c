"""Where whole-uterus requests lose their accept flags: their common offset against their slices' relative placement.

The expected errors are honest on the pose benchmarks' acquisitions and too small on whole-uterus
requests (docs/localisation.md). This script measures, per request, how the slices' error splits
into the request's common rigid offset (one move of all its slices, fitted to their anchor points)
and their placement relative to each other once it is undone, beside what the service knows of the
request: its network error (the frame error's input), its pooled placement's standard error and the
image stage's mismatch after the refinement (``image_consistency.mismatch_after``). It then tries
the mismatch as the input of one more hinge error in quadrature, fitted as the noise and frame errors
are (:func:`~model_export.calibrate_noise.calibrate_hinge`, the acquisitions the reference), and says
what that would do to the accept flags (the model's limit applied to the raised errors).

    .venv/bin/python model_export/experiments/whole_uterus_flags.py --scenes 20 --motion mild
    .venv/bin/python model_export/experiments/whole_uterus_flags.py --scenes 20 --motion drift --seed 2200000

Results: docs/reports/accuracy-analyses.md ("Where whole-uterus requests lose their accept flags").
"""

from __future__ import annotations

import argparse
from collections import defaultdict

import numpy as np
from numpy.typing import NDArray
from scipy.stats import spearmanr

from model_export.acquisitions import simulate_acquisition
from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes, split
from model_export.calibrate_noise import calibrate_hinge, median_ratio
from model_export.evaluate_acquisitions import MIN_MASK_PIXELS, run_acquisition
from model_export.localiser import pose_accuracy as pa
from model_export.localiser.pose_accuracy import pose_estimator
from service.geometry import anchors
from service.geometry.grid import kabsch
from service.pipeline.documents import stack_objects
from service.pipeline.predict import StackPrediction, predict
from service.pipeline.prepare import prepare_stacks
from service.preprocess.localise import default_localiser

MISMATCH_EDGES = (0.0, 0.25, 0.5, 0.75, 1.0, 1.3, 1.7, 9.0)
"""Groups of the requests' image mismatch after refinement (the acquisitions lie under 0.25)."""


def rigid_fit(points: NDArray, truth: NDArray) -> NDArray[np.float64]:
    """The residual distances ``[n]`` of ``points [n, 3]`` once the one rigid move that best brings
    them onto ``truth`` (:func:`~service.geometry.grid.kabsch`) is applied.

    Example (a shifted and turned copy fits exactly):
        >>> rng = np.random.default_rng(0); q = rng.normal(size=(9, 3))
        >>> c, s = np.cos(0.3), np.sin(0.3); r = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        >>> float(rigid_fit(q @ r.T + 5.0, q).max()) < 1e-9
        True
    """
    move = kabsch(points, truth)
    return np.linalg.norm(points @ move[:3, :3].T + move[:3, 3] - truth, axis=1)


def request_rows(group: str, poses: list[NDArray], truths: list[NDArray], answers: list[dict],
                 predictions: list[StackPrediction], rows: dict[str, list]) -> None:
    """Add one request's scored slices to ``rows``: E.D., expected error, accept flag, the request's
    mismatch after refinement, its network error and pooled placement's standard error, and its
    slices' E.D. relative to each other (the common rigid offset undone)."""
    p = anchors.encode(np.concatenate(poses)).reshape(-1, 3)
    q = anchors.encode(np.concatenate(truths)).reshape(-1, 3)
    relative = rigid_fit(p, q).reshape(-1, 3).mean(1)
    ic = next((s.poses.image_consistency for s in predictions if s.poses.image_consistency is not None), None)
    pooled = [s.poses.pooled.placement_sd_mm for s in predictions if s.poses.pooled is not None]
    n = len(relative)
    rows["group"] += [group] * n
    rows["request"].append(np.full(n, len(rows["ed"])))
    rows["ed"].append(anchors.ed(np.concatenate(poses), np.concatenate(truths)))
    rows["relative"].append(relative)
    rows["expected"].append(np.concatenate([a["expected"] for a in answers]))
    rows["accepted"].append(np.concatenate([a["accepted"] for a in answers]))
    for key, value in (("mismatch", np.nan if ic is None else ic.mismatch_after),
                       ("sigma", predictions[0].request_network_error_mm if predictions else np.nan),
                       ("pooled_sd", float(np.mean(pooled)) if pooled else np.nan)):
        rows[key].append(np.full(n, value))


def _answered(answer: dict, keep: NDArray) -> dict:
    slices = [answer["slices"][k] for k in keep]
    expected = [np.nan if s["expected_error_mm"] is None else s["expected_error_mm"] for s in slices]
    return {"expected": np.array(expected),
            "accepted": np.array([bool(s["accepted"]) for s in slices])}


def measure(scenes: int, seed: int, motion: str, acquisitions: int) -> dict[str, NDArray]:
    """Per slice with brain: whole-uterus requests of three stacks planned about the head (the atlas's
    brain masks, and none), and ``acquisitions`` acquisitions a level (mild, moderate, jumps) of each
    validation brain, through ``/v1/predict``'s pipeline."""
    estimator, localiser = pose_estimator(), default_localiser()
    rows: dict[str, list] = defaultdict(list)
    for case in pa.validation_cases(scenes, seed, 3, motion=None if motion == "drift" else motion,
                                    planning="orthogonal"):
        for variant in ("brain", "localiser"):
            prepared = prepare_stacks([pa._upload(s, variant) for s in case], estimator.info, True, workers=1,
                                      localiser=localiser if variant == "localiser" else None)
            predictions, _ = predict(prepared, estimator, 100, estimator.info.variance_threshold)
            poses, truths, answers = [], [], []
            for scene, answer, stack in zip(case, stack_objects(predictions), prepared):
                posed_poses, posed = pa.slice_poses(answer, stack)
                keep = np.flatnonzero(scene.brain.sum(axis=(0, 1)) >= pa.MIN_BRAIN_PIXELS)
                keep = keep[posed[keep]]
                poses.append(posed_poses[keep])
                truths.append((scene.atlas_from_voxel @ np.linalg.inv(stack.slices.slice_from_voxel))[keep])
                answers.append(_answered(answer, keep))
            request_rows(f"scenes {motion}, {variant}", poses, truths, answers, predictions, rows)
    volumes = load_volumes(split(DEFAULT_ATLAS_ROOT)[1], DEFAULT_ATLAS_ROOT)
    for level in ("mild", "moderate", "jumps"):
        for a, vol in enumerate(volumes * acquisitions):
            stacks = simulate_acquisition(vol.image, vol.mask, vol.affine, np.random.default_rng([5, a]), level)
            (predictions,), prepared, truth = run_acquisition(stacks, estimator)
            poses, truths, answers = [], [], []
            for answer, stack, true in zip(stack_objects(predictions), prepared, truth):
                keep = np.flatnonzero(stack.prepared.mask_pixels >= MIN_MASK_PIXELS)
                poses.append(stack.in_network_frame([s["atlas_from_voxel"] for s in answer["slices"]])[keep])
                truths.append(true[keep])
                answers.append(_answered(answer, keep))
            request_rows(f"acquisitions {level}", poses, truths, answers, predictions, rows)
    return {k: np.asarray(v) if k == "group" else np.concatenate(v) for k, v in rows.items()}


def per_request(c: dict[str, NDArray], g: NDArray) -> dict[str, NDArray]:
    """Per request of ``g``: its common and relative error (RMS over its slices; the common part what
    the relative part leaves of the E.D.), its network error, pooled placement's standard error and
    image mismatch."""
    out: dict[str, list] = defaultdict(list)
    for r in np.unique(c["request"][g]):
        m = g & (c["request"] == r)
        out["relative"].append(rms(c["relative"][m]))
        out["common"].append(np.sqrt(max(rms(c["ed"][m]) ** 2 - out["relative"][-1] ** 2, 0.0)))
        for key in ("sigma", "pooled_sd", "mismatch"):
            out[key].append(float(c[key][m][0]))
    return {k: np.asarray(v) for k, v in out.items()}


def rms(x: NDArray) -> float:
    return float(np.sqrt(np.nanmean(np.square(x))))


def report(c: dict[str, NDArray], limit_mm: float) -> None:
    """Per group: accept flags, E.D. against the expected errors, the split of the error; then the
    mismatch hinge fitted on every group and its accept flags."""
    onset, slope, target, _ = calibrate_hinge(c["mismatch"], c["ed"], c["expected"], MISMATCH_EDGES, 0.25,
                                              "mismatch", "acquisitions (mismatch under 0.25)",
                                              np.arange(0.0, 20.01, 0.25), np.arange(0.0, 1.01, 0.05))
    raised = np.hypot(c["expected"], slope * np.maximum(np.nan_to_num(c["mismatch"]) - onset, 0.0))
    flags = c["accepted"] & (raised <= limit_mm)
    print(f"mismatch hinge fitted: onset {onset:.2f}, slope {slope:.2f} mm (reference median ratio {target:.2f})")
    print("| requests | slices | mismatch (median) | accepted | accepted over 10 mm (of the slices over 10 mm) "
          "| of the slices under 5 mm, accepted | RMS E.D. / RMS expected, accepted "
          "| common / relative error (per request, median) "
          "| with the mismatch hinge: accepted, over 10 mm, under 5 mm accepted |")
    print("|---|---|---|---|---|---|---|---|---|")
    for group in dict.fromkeys(c["group"]):
        g = c["group"] == group
        ed, acc, new = c["ed"][g], c["accepted"][g], flags[g]
        bad, good = ed > 10.0, ed < 5.0
        share = lambda f, m: f"{100 * f[m].mean():.0f} %" if m.any() else "-"  # noqa: E731
        requests = per_request(c, g)
        common, relative = float(np.median(requests["common"])), float(np.median(requests["relative"]))
        print(f"| {group} | {g.sum()} | {np.nanmedian(c['mismatch'][g]):.2f} | {acc.sum()} | {(acc & bad).sum()} "
              f"({share(acc, bad)}) | {share(acc, good)} | {rms(ed[acc]) / rms(c['expected'][g][acc]):.2f} "
              f"| {common:.2f} / {relative:.2f} mm | {new.sum()}, {(new & bad).sum()}, {share(new, good)} |")
        print(f"  median ratio E.D. / expected {median_ratio(ed, c['expected'][g]):.2f}", end="; ")
        print(f"with the hinge {median_ratio(ed, raised[g]):.2f}")
    scenes = per_request(c, np.char.startswith(c["group"], "scenes"))
    ranks = {k: spearmanr(scenes["common"], scenes[k], nan_policy="omit")[0] for k in ("sigma", "pooled_sd", "mismatch")}
    print(f"the scene requests' common error ranked by (Spearman, {len(scenes['common'])} requests): "
          + ", ".join(f"{k} {v:.2f}" for k, v in ranks.items()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=20)
    ap.add_argument("--seed", type=int, default=2_000_000)
    ap.add_argument("--motion", default="mild", help="a pose benchmark's level, or drift (the generator's own)")
    ap.add_argument("--acquisitions", type=int, default=2, help="acquisitions a level of each validation brain")
    args = ap.parse_args()
    limit = float(pose_estimator().info.max_expected_error_mm)
    report(measure(args.scenes, args.seed, args.motion, args.acquisitions), limit)


if __name__ == "__main__":
    main()
