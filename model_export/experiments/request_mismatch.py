"""A request whose images still disagree after the image stage: does its remaining mismatch tell
when every slice's expected error is too small?

The stages judge each slice's remaining image mismatch against the request's median, so a request
whose slices agree nowhere (a signal void that biases the network alike in every stack) looks
normal to them, and its slices keep expected errors that are too small. The image stage's
remaining mismatch for the whole request (``mismatch_after``, per weighted point, in units of its
noise) does not depend on that median. This script runs ``/v1/predict``'s stages on cached network
outputs (:mod:`model_export.experiments.stage_variants`; a cache made with ``--void`` holds the
void) and prints, per cache and motion level, the range of that mismatch and its fall through the
stage, then what every slice's expected error times ``max(1, mismatch_after / M0) ** G`` would
accept (good: E.D. under 5 mm, bad: over 10 mm) and the RMS E.D. over the RMS expected error.
With ``--real DIR`` it prints the same mismatch for a real scan's answers with its manual masks and
without them (the model's fixed draws of seed 0 and 1): where real scans lie against the caches.
With ``--job-floor DIR`` it prints, for a real scan with its manual masks, the same image term at
``/v1/predict``'s final poses and at the poses a reconstruction job refines from them (slice-to-
volume registration): where both lie alike, the scan's mismatch is its own floor (its images disagree
at the best poses anyone finds), not an error of the poses. ``--at-truth`` prints, for every third
cached acquisition, the term at the service's poses, refined further from them, and at the true
poses: what the images leave where the poses are right. ``--dark M0,...`` judges the caches with
a request's share of dark pixels (:func:`dark_share`, its 90th percentile over the request's slices)
in place of its mismatch, each ``M0`` a reference of that factor.

    .venv/bin/python model_export/experiments/stage_variants.py --cache /tmp/void-21.pkl --seed 21 --void \\
        --levels mild,moderate,jumps --per-volume 2 base                                   # makes the cache
    .venv/bin/python model_export/experiments/request_mismatch.py /tmp/stages-21.pkl /tmp/void-21.pkl \\
        [--factors 0.2:0.5,0.5:1] [--real ../shared/data/real_scans/mial_lausanne_t30] \\
        [--job-floor ../shared/data/real_scans/mial_lausanne_t30] [--at-truth] [--dark 0.1,0.15]
"""

from __future__ import annotations

import argparse
import pickle
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.evaluate_acquisitions import MIN_MASK_PIXELS  # noqa: E402
from model_export.experiments.stage_variants import calibrated_as  # noqa: E402
from service.geometry.anchors import ed  # noqa: E402
from service.inference.model_file import ModelInfo, load_model  # noqa: E402
import service.pipeline.predict as pipeline  # noqa: E402
from service.pipeline import image_stage  # noqa: E402


@dataclass
class Request:
    """One cached acquisition through the stages: its image stage's mismatch before and after, and
    per slice its E.D. against the truth, whether it was accepted and its expected error."""

    cache: str
    level: str
    before: float
    after: float
    ed_mm: NDArray[np.float64]
    accepted: NDArray[np.bool_]
    expected_mm: NDArray[np.float64]


def factor(after: float, m0: float, power: float) -> float:
    """``max(1, after / m0) ** power`` (1 where the request has no image stage).

    Example:
        >>> factor(1.0, 0.5, 1.0), factor(0.2, 0.5, 1.0), factor(float("nan"), 0.5, 1.0)
        (2.0, 1.0, 1.0)
    """
    return 1.0 if not np.isfinite(after) else max(1.0, after / m0) ** power


def judged(requests: list[Request], limit_mm: float, m0: float | None, power: float) -> dict[str, float]:
    """What the accept flags keep with every expected error of a request times :func:`factor`
    (``m0`` None: as they are): shares of good (< 5 mm) and bad (> 10 mm) slices accepted, the bad
    slices' count and RMS E.D. over RMS expected error.

    Example:
        >>> r = Request("c", "mild", 1.0, 1.0, np.array([2.0, 12.0]), np.array([True, True]), np.array([3.0, 3.0]))
        >>> judged([r], 4.8, None, 1.0)["bad_accepted"], judged([r], 4.8, 0.5, 1.0)["bad_accepted"]
        (1.0, 0.0)
    """
    e = np.concatenate([r.ed_mm for r in requests])
    grown = np.concatenate([r.expected_mm * (1.0 if m0 is None else factor(r.after, m0, power)) for r in requests])
    accepted = np.concatenate([r.accepted for r in requests]) & ~(grown > limit_mm)
    known = np.isfinite(grown)
    return {"good_accepted": float(np.mean(accepted[e < 5])) if (e < 5).any() else np.nan,
            "bad_accepted": float(np.mean(accepted[e > 10])) if (e > 10).any() else np.nan,
            "bad_slices": int((e > 10).sum()),
            "rms_ratio": float(np.sqrt(np.mean(e[known] ** 2) / np.mean(grown[known] ** 2))) if known.any() else np.nan}


@dataclass
class Cache:
    """A ``stage_variants.py`` cache read once, its calibration ``model``'s, and every acquisition's
    answer through the stages (``predictions``, in the order of ``cases``)."""

    name: str
    info: ModelInfo
    cases: list
    predictions: list

    @classmethod
    def read(cls, path: Path, model: ModelInfo) -> "Cache":
        with open(path, "rb") as f:
            info, cases = pickle.load(f)                                               # noqa: S301 - our own file
        info = calibrated_as(info, model)
        return cls(path.name, info, cases, [pipeline.predict_from_estimates(prepared, parts, info, info.variance_threshold)[0]
                                            for _, prepared, parts, _ in cases])


def cached_requests(cache: Cache) -> list[Request]:
    """Every acquisition of ``cache`` as a :class:`Request`: its stage's mismatch, and per slice its E.D.,
    accept flag and expected error."""
    out = []
    for (level, _, _, truth), predictions in zip(cache.cases, cache.predictions):
        stage = next((p.poses.image_consistency for p in predictions if p.poses.image_consistency is not None), None)
        keep = [p.prepared.prepared.mask_pixels >= MIN_MASK_PIXELS for p in predictions]
        out.append(Request(
            cache.name, level, np.nan if stage is None else stage.mismatch_before,
            np.nan if stage is None else stage.mismatch_after,
            np.concatenate([ed(p.poses.poses, t)[k] for p, t, k in zip(predictions, truth, keep)]),
            np.concatenate([np.array([r is None for r in p.reasons])[k] for p, k in zip(predictions, keep)]),
            np.concatenate([np.full(k.sum(), np.nan) if p.poses.expected_error_mm is None else p.poses.expected_error_mm[k]
                            for p, k in zip(predictions, keep)])))
    return out


def real_mismatch(scan: Path) -> None:
    """A real scan's answers with its manual masks and without them: the image stage's remaining mismatch."""
    from model_export.experiments import mask_vote, real_scan_poses
    from model_export.localiser.pose_accuracy import pose_estimator
    from service.inference.estimator import OnnxPoseEstimator

    base = pose_estimator(None)
    volumes, manual = real_scan_poses.read_scan(scan)
    for seed in (0, 1):
        estimator = base if seed == 0 else OnnxPoseEstimator(base.model.with_seed(base.model.mc_seed + seed))
        for variant in (None, "none"):
            stacks, _ = mask_vote.answer(volumes, manual, estimator, variant)
            after = [(s["consistency"].get("image_consistency") or {}).get("mismatch_after") for s in stacks]
            print(f"{scan.name}, seed {seed}, {'manual masks' if variant is None else 'no masks'}: mismatch after "
                  f"{[None if m is None else round(m, 2) for m in after]}", flush=True)


def mismatch_at(prepared: list, active: list[NDArray], poses: list[NDArray]) -> tuple[float, float]:
    """The image stage's term (per weighted point, :attr:`~service.consistency.image_refinement.Refinement.cost_after`)
    at ``poses`` (per stack ``[n, 4, 4]``, network frame -> atlas) over the slices ``active``, and after the
    stage refines them further from there (a prior of 3 mm per slice)."""
    from service.consistency.image_refinement import refine

    images = [image_stage.stack_images(p, a) for p, a in zip(prepared, active)]
    expected = [np.full(len(p), 3.0) for p in poses]
    return refine(images, poses, expected, iterations=0).cost_after, refine(images, poses, expected).cost_after


DARK = 0.5
"""A pixel of a slice's mask is dark under this share of its stack's median brain intensity."""


def dark_share(prepared: list) -> NDArray[np.float64]:
    """Per slice of the prepared stacks, in order, the share of its mask's pixels darker than
    :data:`DARK` times its stack's median brain intensity (NaN for a slice of 50 mask pixels or fewer):
    where a void or shading has darkened the brain.

    Example (one stack: a slice half darkened, one not, one without brain):
        >>> from types import SimpleNamespace
        >>> images = np.full((3, 10, 10), 100.0); images[0, :5] = 20.0
        >>> masks = np.ones((3, 10, 10), bool); masks[2] = False
        >>> dark_share([SimpleNamespace(slices=SimpleNamespace(images=images, masks=masks))]).tolist()
        [0.5, 0.0, nan]
    """
    out = []
    for p in prepared:
        images, masks = p.slices.images, p.slices.masks
        median = float(np.median(images[masks])) if masks.any() else 1.0
        out += [float((image[mask] < DARK * median).mean()) if mask.sum() > 50 else np.nan
                for image, mask in zip(images, masks)]
    return np.array(out)


def dark_requests(cache: Cache, requests: list[Request]) -> list[Request]:
    """``cache``'s :func:`cached_requests` ``requests`` with each one's 90th percentile of
    :func:`dark_share` in place of its remaining mismatch (the factor's input)."""
    shares = [float(np.nanpercentile(dark_share(prepared), 90)) for _, prepared, _, _ in cache.cases]
    return [replace(r, after=share) for r, share in zip(requests, shares)]


def truth_floor(cache: Cache, every: int = 3) -> None:
    """Every ``every``-th acquisition of ``cache``: the image term at the service's final poses, refined
    further from them, and at the true poses; and the poses' mean E.D."""
    for (level, prepared, _, truth), predictions in list(zip(cache.cases, cache.predictions))[::every]:
        active = [np.isfinite(p.estimate.spread_mm) for p in predictions]
        poses = [p.poses.poses for p in predictions]
        at, further = mismatch_at(prepared, active, poses)
        at_truth, _ = mismatch_at(prepared, active, truth)
        error = np.concatenate([ed(p, t) for p, t in zip(poses, truth)])
        print(f"{cache.name} {level}: mismatch at the service's poses {at:.2f}, refined further {further:.2f}, "
              f"at the truth {at_truth:.2f}; mean E.D. {error.mean():.1f} mm", flush=True)


def job_floor(scan: Path) -> None:
    """A real scan with its manual masks: the image term at ``/v1/predict``'s final poses, at its
    stack stage's poses, and at the poses a reconstruction job (its never-worse slice-to-volume
    refinement, 1.5 mm) takes them to, before and after its frame steps."""
    from model_export.experiments import real_scan_poses
    from model_export.localiser.pose_accuracy import pose_estimator
    from service.jobs.uploaded_poses import expected_errors
    from service.jobs.starting_poses import starting_poses
    from service.jobs.worker import predicted_body
    from service.pipeline.prepare import StackUpload, prepare_stacks
    from service.preprocess.localise import default_localiser
    from service.reconstruction.job import refine_job
    from service.reconstruction.slices import SliceSet

    estimator, localiser = pose_estimator(None), default_localiser()
    volumes, manual = real_scan_poses.read_scan(scan)
    uploads = [StackUpload(n, volumes[n], manual[n], f"{n}_brain_mask", mask_holds_csf=True) for n in volumes]
    prepared = prepare_stacks(uploads, estimator.info, True, workers=2, localiser=localiser)
    print(f"{scan.name}, manual masks: 90th percentile of dark pixels {np.nanpercentile(dark_share(prepared), 90):.3f}")
    parts, _ = pipeline.estimate_stacks(prepared, estimator, 100)              # the network once for both answers
    answers = {stage: pipeline.predict_from_estimates(prepared, parts, estimator.info, estimator.info.variance_threshold,
                                                      image_consistency=stage)[0] for stage in (True, False)}
    active = [np.isfinite(p.estimate.spread_mm) for p in answers[True]]
    network_from_voxel = [p.network_from_voxel() for p in prepared]
    body, masks = predicted_body(uploads, estimator, 100, localiser=localiser)
    inputs = [(u.volume, m, mats, acc) for u, m, (mats, acc) in zip(uploads, masks, starting_poses(body))]
    job = refine_job(SliceSet.from_stacks(inputs), inputs, expected_errors(body), estimator=estimator,
                     plane_x_mm=estimator.info.symmetry_plane_x_mm, resolution_mm=1.5, svr_iterations=3)
    bounds = np.cumsum([0] + [len(n) for n in network_from_voxel])

    def in_network_frames(atlas_from_voxel: NDArray) -> list[NDArray]:
        return [np.asarray(atlas_from_voxel)[a:b] @ np.linalg.inv(n)
                for a, b, n in zip(bounds[:-1], bounds[1:], network_from_voxel)]

    rows = {"/v1/predict's final poses": [p.poses.poses for p in answers[True]],
            "its stack stage's poses (no image stage)": [p.poses.poses for p in answers[False]],
            "the job's, before its frame steps": in_network_frames(job.left_out.poses),
            "the job's, as it returns them": in_network_frames(job.result.atlas_from_voxel_final)}
    for label, poses in rows.items():
        at, refined = mismatch_at(prepared, active, poses)
        print(f"{scan.name}, manual masks, {label}: mismatch {at:.3f}, refined further {refined:.3f}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("caches", type=Path, nargs="*")
    ap.add_argument("--factors", default="0.2:0.5,0.3:1,0.5:1", help="M0:G pairs, comma-separated")
    ap.add_argument("--real", type=Path, action="append", default=[])
    ap.add_argument("--job-floor", type=Path, action="append", default=[])
    ap.add_argument("--at-truth", action="store_true", help="the mismatch at the true poses of the caches' acquisitions")
    ap.add_argument("--dark", help="references M0 of a factor on the request's share of dark pixels, comma-separated")
    ap.add_argument("--model", type=Path, default=Path("service/models/default/model.onnx"))
    args = ap.parse_args()
    model = load_model(args.model).info
    limit = model.max_expected_error_mm
    requests, dark = [], []
    for path in args.caches:                      # one cache in memory at a time, through the stages once
        cache = Cache.read(path, model)
        found = cached_requests(cache)
        requests += found
        if args.dark:
            dark += dark_requests(cache, found)
        if args.at_truth:
            truth_floor(cache)
        del cache
    groups = sorted({(r.cache, r.level) for r in requests})
    for cache_name, level in groups:
        rows = [r for r in requests if (r.cache, r.level) == (cache_name, level)]
        after = np.array([r.after for r in rows])
        fall = after / np.array([r.before for r in rows])
        print(f"{cache_name} {level}: mismatch after {np.nanmin(after):.2f}-{np.nanmax(after):.2f}, "
              f"after / before {np.nanmin(fall):.2f}-{np.nanmax(fall):.2f}")
    for spec in [None, *args.factors.split(",")]:
        m0, power = (None, 1.0) if spec is None else (float(spec.split(":")[0]), float(spec.split(":")[1]))
        print("as the service" if spec is None else f"expected errors x max(1, after / {m0}) ** {power}")
        for cache_name, level in groups:
            got = judged([r for r in requests if (r.cache, r.level) == (cache_name, level)], limit, m0, power)
            print(f"  {cache_name} {level}: good accepted {got['good_accepted']:.0%}, bad accepted {got['bad_accepted']:.0%} "
                  f"of {got['bad_slices']}, RMS E.D. / RMS expected {got['rms_ratio']:.2f}")
    for cache_name in dict.fromkeys(r.cache for r in dark):
        rows = [r for r in dark if r.cache == cache_name]
        share = [r.after for r in rows]
        print(f"{cache_name}: a request's 90th percentile of dark pixels {min(share):.3f}-{max(share):.3f}")
        for m0 in [None, *(float(x) for x in args.dark.split(","))]:
            for level in sorted({r.level for r in rows}):
                got = judged([r for r in rows if r.level == level], limit, m0, 1.0)
                print(f"  {'as the service' if m0 is None else f'x max(1, dark / {m0})'} {level}: good accepted "
                      f"{got['good_accepted']:.0%}, bad accepted {got['bad_accepted']:.0%} of {got['bad_slices']}")
    for scan in args.real:
        real_mismatch(scan)
    for scan in args.job_floor:
        job_floor(scan)


if __name__ == "__main__":
    main()
