"""A reconstruction job that keeps the poses it started from unless registration does clearly better.

Slice-to-volume registration can diverge: under motion that jumps, or that is independent from
slice to slice, a stack is no rigid body, and the coarse steps that treat it as one
(:mod:`~service.reconstruction.coarse_to_fine`) move good predicted poses far away; the rounds then
refine a scrambled volume (``model_export/experiments/refine_bench.py`` ablates each stage). Which
path a scan needs is not known in advance, and there is no truth to ask. The quality report is the
judge (:mod:`~service.reconstruction.quality`): how well the volume without each stack predicts
that stack's slices, at the poses the path returns.

Paths, in order:

1. **the full job** (the configuration as given);
2. **the starting poses**: robust super-resolution at the poses the job was given, no registration;
3. **slice level only** (no coarse steps), when the full job has its coarse steps on. It is tried
   even where the full job beats the starting poses: at extreme motion the coarse steps can scramble
   the slices and still score above poses that far off, while the slice level scores higher still;
4. **further slice-level passes** (:data:`MAX_FURTHER_PASSES`), where a registered path won:
   the slice level again, from the poses the last kept pass returned. Registration under
   large motion has not converged after one pass (its trust region moves each slice a few mm a
   round), and a pass that starts nearer the answer gets further. A further pass has no coarse
   step, so no slice restarts from its stack's pose and no round widens its trust radius.

Where the job asks for a volume finer than :data:`PATH_RESOLUTION_MM`, the paths and passes run at
that resolution (they decide where the slices go, and a 1.5 mm grid holds a sixth of the voxels of
a 0.8 mm one), and one more pass solves the volume at the resolution asked for
(:func:`at_output_resolution`): the slice level again from the chosen poses where a registered path
won, else the robust super-resolution at the starting poses; a choice the starting poses won by a
small margin is made again there.

A registered path (1 or 3) wins where its leave-one-stack-out mismatch (1 - the median NCC) is at
most the starting poses' over :data:`MIN_MISMATCH_RATIO` (more where the score rests on fewer than
:data:`REFERENCE_SLICES` slices: :func:`required_ratio`) and its stacks predict each other
(:data:`~service.reconstruction.quality.MIN_HELD_OUT_NCC`); otherwise the starting poses do. A
further pass is kept by the same rule against the pass it started from; the first that is not ends
them. The quality report names the winner (``path``), every path's score (``paths``) and the
further passes' scores and how many were kept (``further_passes``), the paths' resolution
(``path_resolution_mm``) and, where the output pass ran, what it did (``output_pass``); its other
fields describe the result returned. A slice the winner's stack fit found inconsistent with its
stack keeps that verdict (``stack_outlier``) in a kept pass that leaves it out. A job of one stack
has nothing to leave out: it keeps the full job (and, at a finer output resolution, the slice level
from its poses, unjudged).

Example:
    >>> choose({"full": 0.80, "starting_poses": 0.93, "slice_level": 0.935})
    'starting_poses'
    >>> choose({"full": 0.95, "starting_poses": 0.93})
    'full'
    >>> choose({"full": 0.45, "starting_poses": 0.48, "slice_level": 0.81})
    'slice_level'
    >>> choose({"full": None, "starting_poses": 0.9})
    'full'
    >>> scores = {"full": 0.8248, "starting_poses": 0.7958}               # 1.17 x less mismatch
    >>> choose(scores), choose(scores, required_ratio(slices=28))
    ('full', 'starting_poses')
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike

from service.reconstruction.grid import bounds_of, bounds_within
from service.reconstruction.config import ReconstructionConfig
from service.reconstruction.pipeline import Progress, ReconstructionResult, reconstruct
from service.reconstruction.held_out import held_out_score
from service.reconstruction.quality import exclusion_reasons, incoherent
from service.reconstruction.slices import SliceSet

PATHS = ("full", "starting_poses", "slice_level")
MIN_MISMATCH_RATIO = 1.15
"""How many times smaller than the starting poses' a registered path's leave-one-stack-out mismatch
(1 - median NCC) must be for it to be taken: the score's noise grows with the mismatch, so the gain
asked for does too. The ratio lies between what a registered path that does not make the poses
better reaches (mild to independent motion) and what one that does reaches (extreme motion, the
shared real scan with its masks): the ratios measured are in docs/reports/reconstruction-experiments.md,
"The figures behind the job's constants"."""

REFERENCE_SLICES = 60
"""The held-out slices at which a job's score is judged by :data:`MIN_MISMATCH_RATIO` as it is: the
sets it was chosen on start from about this many slices. A median over fewer is noisier (as one
over the square root of their number), so a path asks for more (:func:`required_ratio`; the
acquisitions it was judged on: docs/reports/reconstruction-experiments.md)."""


MAX_FURTHER_PASSES = 1
"""Slice-level passes tried after a registered path wins. The first further pass cuts the held-out
mismatch and the slices' error where the motion is extreme; a second one gains less than
:data:`MIN_MISMATCH_RATIO` asks and costs as much again. From the starting poses at mild motion no
pass cuts it (registration makes those poses worse): hence only after a registered path has won
(the runs: docs/reports/reconstruction-experiments.md, "The figures behind the job's constants")."""

PATH_RESOLUTION_MM = 1.5
"""The resolution the paths and further passes run at when the job asks for a finer volume (the
volume returned is solved at the finer one, at the poses they chose)."""
UNDECIDED_POWER = 0.5
"""Where the starting poses won at the paths' resolution but a registered path cut their mismatch at
least the ratio asked to this power, the choice is made again at the output resolution
(:func:`at_output_resolution`): a coarse grid compresses the ratio (on the shared real scan the full
path's is about its square root at 1.5 mm of what it is at 0.8 mm)."""
OUTPUT_SHARE = 0.7
"""The share of a job's progress the paths take when the volume is then solved at a finer resolution."""


def held_out_slices(result: ReconstructionResult) -> int | None:
    """How many slices the result's leave-one-stack-out score rests on (None: not known)."""
    if result.quality is None:
        return None
    return result.quality["leave_one_stack_out"].get("slices")


def required_ratio(slices: int | None, ratio: float = MIN_MISMATCH_RATIO) -> float:
    """The mismatch ratio asked of a score over ``slices`` held-out slices: ``ratio`` from
    :data:`REFERENCE_SLICES` on (or where the count is not known), ``ratio ** sqrt(REFERENCE_SLICES
    / slices)`` below (the log-ratio's noise grows as one over the square root of the count).

    Example:
        >>> [round(required_ratio(n), 3) for n in (None, 120, 60, 28, 15)]
        [1.15, 1.15, 1.15, 1.227, 1.322]
    """
    if not slices or slices >= REFERENCE_SLICES:
        return ratio
    return float(ratio ** np.sqrt(REFERENCE_SLICES / slices))


def choose(scores: dict[str, float | None], ratio: float = MIN_MISMATCH_RATIO) -> str:
    """The registered path with the highest score where its mismatch is ``ratio`` times smaller
    than the starting poses' (:func:`required_ratio` of the slices the scores rest on) and its
    volume a coherent brain (:func:`~service.reconstruction.quality.incoherent`: registration whose
    stacks do not predict each other has not shown it did better, e.g. against a stack whose
    contrast defeats the NCC), else the starting poses; ``full`` when it has no score (nothing to
    compare).

    Example (every path incoherent: the poses the job was given stand):
        >>> choose({"full": 0.41, "starting_poses": 0.18, "slice_level": 0.3})
        'starting_poses'
    """
    if scores.get("full") is None:
        return "full"
    best = best_registered(scores)
    start = scores.get("starting_poses")
    if start is None:
        return best
    return best if clearly_better(scores[best], start, ratio) and not incoherent(scores[best]) else "starting_poses"


def best_registered(scores: dict[str, float | None]) -> str | None:
    """The registered path with the highest score (``full`` on a tie; None: none has a score)."""
    registered = {k: v for k, v in scores.items() if v is not None and k != "starting_poses"}
    return max(registered, key=lambda k: (registered[k], k == "full"), default=None)


def clearly_better(score: float, than: float, ratio: float = MIN_MISMATCH_RATIO) -> bool:
    """Whether held-out median NCC ``score`` leaves at most ``1 / ratio`` of the mismatch (1 - NCC)
    of ``than``.

    Example:
        >>> clearly_better(0.957, 0.95), clearly_better(0.955, 0.95), clearly_better(0.957, 0.95, required_ratio(20))
        (True, False, False)
    """
    return (1.0 - score) * ratio <= 1.0 - than


def reconstruct_never_worse(slice_set: SliceSet, resolution_mm: float = 0.8, svr_iterations: int = 3,
                            progress: Progress | None = None, cancel: Callable[[], bool] | None = None, *,
                            bounds_mm: ArrayLike | None = None, config: ReconstructionConfig | None = None,
                            path_resolution_mm: float | None = PATH_RESOLUTION_MM) -> ReconstructionResult:
    """:func:`~service.reconstruction.pipeline.reconstruct` along the paths of the module: the
    winner, or its last kept further pass, is returned; its ``quality`` says which path won
    (``path``), every path's score (``paths``), what the further passes did (``further_passes``:
    their ``scores`` and how many were ``kept``) and the resolution they ran at
    (``path_resolution_mm``); ``timings["all_paths"]`` is every path's and pass's.

    The paths run at ``path_resolution_mm`` where that is coarser than ``resolution_mm`` (None: at
    ``resolution_mm``); the volume returned is then solved at ``resolution_mm``
    (:func:`at_output_resolution`), and ``quality`` says what that pass did (``output_pass``)."""
    cfg = replace(config or ReconstructionConfig(), quality=True)
    if svr_iterations <= 0:       # no registration round: the robust volume of the starting poses, not their average
        cfg, svr_iterations = replace(cfg, register=False), 1
    results: dict[str, ReconstructionResult] = {}
    scores: dict[str, float | None] = {}
    registers = cfg.register and svr_iterations > 0
    working = max(resolution_mm, path_resolution_mm or 0.0) if registers else resolution_mm
    share = 1.0 if working == resolution_mm else OUTPUT_SHARE

    def run(name: str, run_cfg: ReconstructionConfig, lo: float, hi: float) -> None:
        label = None if name == "full" else f"checking {name.replace('_', ' ')}"
        part = None if progress is None else (lambda stage, f: progress(label or stage, share * (lo + (hi - lo) * f)))
        results[name] = reconstruct(slice_set, working, svr_iterations, part, cancel, bounds_mm=bounds_mm,
                                    config=run_cfg)
        scores[name] = held_out_score(results[name])

    slice_level = registers and cfg.coarse_to_fine
    run("full", cfg, 0.0, 0.45 if slice_level else 0.75)
    if registers and scores["full"] is not None:
        run("starting_poses", replace(cfg, register=False), *((0.45, 0.55) if slice_level else (0.75, 0.85)))
        if slice_level:
            run("slice_level", replace(cfg, coarse_to_fine=False), 0.55, 0.85)
    counted = results["starting_poses"] if "starting_poses" in results else results["full"]
    ratio = required_ratio(held_out_slices(counted))         # what a path must gain, over the slices scored
    best = choose(scores, ratio)
    result = results[best]
    seconds = _seconds(*results.values())
    further: list[float | None] = []
    kept = 0
    if registers and best != "starting_poses" and scores[best] is not None:
        again_cfg = replace(cfg, coarse_to_fine=False)
        for k in range(MAX_FURTHER_PASSES):
            lo = 0.85 + 0.15 * k / MAX_FURTHER_PASSES
            part = None if progress is None else (lambda stage, f, lo=lo: progress(
                "further slice-level pass", share * (lo + 0.15 / MAX_FURTHER_PASSES * f)))
            again = reconstruct(replace(slice_set, atlas_from_voxel=result.atlas_from_voxel_final), working,
                                svr_iterations, part, cancel, bounds_mm=bounds_mm, config=again_cfg)
            seconds += again.timings.get("total", 0.0)
            score = held_out_score(again)
            further.append(score)
            if score is None or not clearly_better(score, held_out_score(result), ratio):
                break
            result, kept = again, kept + 1
    output_pass = None
    if working != resolution_mm:
        part = None if progress is None else (
            lambda stage, f: progress("volume at the output resolution", share + (1.0 - share) * f))
        result, best, output_pass, spent = at_output_resolution(slice_set, results, scores, best, result,
                                                                resolution_mm, svr_iterations, part, cancel,
                                                                bounds_mm, cfg, ratio)
        seconds += spent
    if (kept or output_pass is not None) and results[best].coarse is not None:   # the winner's stack fit still judges
        result.coarse = results[best].coarse
        result.exclusion_reason = exclusion_reasons(slice_set.include, result.included, result.coarse.fit.inlier)
    if not registers:             # one path, which moved no slice: the starting poses' volume
        best, scores = "starting_poses", {"starting_poses": scores["full"]}
    result.quality = {**result.quality, "path": best, "paths": scores,
                      "further_passes": {"scores": further, "kept": kept}, "path_resolution_mm": working,
                      **({"output_pass": output_pass} if output_pass is not None else {})}
    result.timings = {**result.timings, "all_paths": seconds}
    if progress is not None:
        progress("done", 1.0)
    return result


def at_output_resolution(slice_set: SliceSet, results: dict[str, ReconstructionResult],
                         scores: dict[str, float | None], best: str, chosen: ReconstructionResult,
                         resolution_mm: float, svr_iterations: int, progress: Progress | None,
                         cancel: Callable[[], bool] | None, bounds_mm: ArrayLike | None,
                         config: ReconstructionConfig, ratio: float = MIN_MISMATCH_RATIO,
                         ) -> tuple[ReconstructionResult, str, dict, float]:
    """The volume at ``resolution_mm`` after the paths ran at a coarser one (``results`` and their
    ``scores``; ``best`` the path they chose, ``chosen`` its result or its last kept further pass);
    returns it, the path it follows, what the output pass did (``output_pass``: ``tried``,
    ``score``, ``kept`` and, where it was judged against another volume, ``against``: that volume's
    score) and the seconds its solves took. ``ratio``: the mismatch ratio a volume must gain
    (:func:`required_ratio`).

    * A registered path won: the slice level again at ``resolution_mm`` from its poses (the
      registration sees the finer volume's detail). Where its leave-one-stack-out mismatch is
      ``ratio`` times that of ``chosen``, the robust super-resolution at those poses is solved
      too, and the pass is kept unless that volume does clearly better at the same resolution
      (scores of two resolutions are not alike: see :data:`UNDECIDED_POWER`).
    * The starting poses won, but a coherent registered path cut their mismatch by at least
      ``ratio`` to the power :data:`UNDECIDED_POWER`: a coarse grid shows a pose's gain less (its
      volumes are blurrier), so the choice is made again at ``resolution_mm``, by the same rule,
      between the starting poses' volume and that path's slice level from its poses.
    * Otherwise: the robust super-resolution at the starting poses.

    Each volume's slice weights, exclusions and quality report are measured on it. Its field of
    view is ``bounds_mm``, else the pixels' box at its poses (and the margin), as the paths draw
    it, within the field of view of the path the poses come from."""
    def solve(source: ReconstructionResult, register: bool, lo: float, hi: float) -> ReconstructionResult:
        poses = source.atlas_from_voxel_final
        bounds = bounds_mm if bounds_mm is not None else \
            bounds_within(bounds_of(slice_set.positions(poses), config.margin_mm), source.grid.bounds_mm)
        part = None if progress is None else (lambda stage, f: progress(stage, lo + (hi - lo) * f))
        run_cfg = replace(config, coarse_to_fine=False) if register else replace(config, register=False)
        return reconstruct(replace(slice_set, atlas_from_voxel=poses), resolution_mm, svr_iterations, part, cancel,
                           bounds_mm=bounds, config=run_cfg)

    if best != "starting_poses":
        fine = solve(chosen, True, 0.0, 0.8)
        score, before = held_out_score(fine), held_out_score(chosen)
        if score is None or before is None or not clearly_better(before, score, ratio):
            return fine, best, {"tried": True, "score": score, "kept": True}, _seconds(fine)
        plain = solve(chosen, False, 0.8, 1.0)
        against = held_out_score(plain)
        kept = against is None or not clearly_better(against, score, ratio)
        return (fine if kept else plain), best, {"tried": True, "score": score, "kept": kept, "against": against}, \
            _seconds(fine, plain)
    start, contender = scores["starting_poses"], best_registered(scores)
    if contender is None or start is None or incoherent(scores[contender]) \
            or not clearly_better(scores[contender], start, ratio ** UNDECIDED_POWER):
        plain = solve(chosen, False, 0.0, 1.0)
        return plain, best, {"tried": False, "score": None, "kept": False}, _seconds(plain)
    plain = solve(chosen, False, 0.0, 0.3)
    fine = solve(results[contender], True, 0.3, 1.0)
    score, against = held_out_score(fine), held_out_score(plain)
    kept = score is not None and against is not None and clearly_better(score, against, ratio) and not incoherent(score)
    return (fine if kept else plain), (contender if kept else best), \
        {"tried": True, "score": score, "kept": kept, "against": against}, _seconds(fine, plain)


def _seconds(*results: ReconstructionResult) -> float:
    """The seconds ``results`` took, together."""
    return sum(r.timings.get("total", 0.0) for r in results)
