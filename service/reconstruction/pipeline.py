"""Slice-to-volume reconstruction: Gaussian average, then rounds of registration, robust weighting and
super-resolution.

::

    binning: slices with pixels <= 0.75 x the voxel size are averaged over 2 x 2 in-plane blocks
            (SliceSet.binned; real size: 1.4 M pixels -> 0.36 M for every stage below)
    coarse: stack rigid fit -> stack-to-stack registration (4 -> 2 -> 1 mm) -> each slice starts
            from its own pose or its stack's, whichever fits the other stacks better
            (coarse_to_fine.py; only with ``config.coarse_to_fine``)
    x = GaussianAverage(slices at the starting poses)
    round 0: g = slice intensities onto A x; W = robust weights of g s - A x;
             x = SR(x, lambda_initial)                                  (smooth sharpening)
    rounds 1..svr_iterations:
        poses = register all slices to x                   (registration.py; by folds of stacks,
                                                            each to x re-solved without that fold;
                                                            the first rounds with a wide trust
                                                            radius against a blurred x)
        poses = anchor_frame(poses)                        (no common rigid drift)
        A = forward model at the new poses                 (forward.py)
        g = each slice's gain and shading onto A x         (intensity.py)
        W = EM inlier probabilities x slice weights of g s - A x   (robust.py)
        x = CG on (A^T W A + lambda D^T Omega D) x = A^T W g s    (superresolution.py)

Registering against the Gaussian average itself would bias the poses (a blurred target pulls the
slices inwards), hence round 0. Leaving a slice's own stacks out of the volume it is registered to
keeps a misplaced slice from being held in place by its own imprint. ``lambda`` decreases from
``lam_first`` to ``lam`` over the rounds.

The function is numpy/scipy only and reports progress through a callback (which may raise to stop
the job); ``cancel`` is polled between stages and raises :class:`Cancelled`.

Example (a tiny, flat input; see the tests for real ones):
    >>> import numpy as np
    >>> from service.io.volume import Volume
    >>> from service.reconstruction.slices import SliceSet, inplane_bin_factors
    >>> vol = Volume(np.ones((12, 12, 6), np.float32), np.diag([1.0, 1.0, 2.0, 1.0]))
    >>> ss = SliceSet.from_stacks([(vol, None, np.repeat(vol.affine[None], 6, 0), np.ones(6, bool))])
    >>> res = reconstruct(ss, resolution_mm=1.0, svr_iterations=0)
    >>> res.volume.array.ndim, bool(res.included.all())
    (3, True)
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core.errors import Cancelled
from service.io.volume import Volume
from service.reconstruction.coarse_to_fine import START_OWN, CoarseAlignment, coarse_align
from service.reconstruction.config import ReconstructionConfig
from service.reconstruction.forward import ForwardModel, inplane_sigma_mm
from service.reconstruction.gaussian_average import compact_brain, gaussian_average
from service.reconstruction.grid import Grid, bounds_of, bounds_within, check_volume_size, make_grid
from service.reconstruction.intensity import SliceIntensity, fit_intensity
from service.reconstruction.registration import anchor_frame, register_slices
from service.reconstruction.quality import (exclusion_reasons, held_out_groups, held_out_ncc, judged_slices,
                                           live_stacks, quality_report, slice_ncc)
from service.reconstruction.robust import ncc_outliers, robust_weights
from service.reconstruction.slices import SliceSet, inplane_bin_factors
from service.reconstruction.superresolution import default_delta, solve_without, super_resolve

Progress = Callable[[str, float], None]
WIDE_CAPTURE_FRACTION = 0.5
"""The wide capture schedule runs when at least this fraction of the slices start from their stack's pose."""


@dataclass
class ReconstructionResult:
    """Output of :func:`reconstruct`.

    Attributes:
        volume: the reconstruction in atlas space (RAS affine, float32; 0 outside the covered region).
        atlas_from_voxel_final: ``[n, 4, 4]`` refined slice transforms (the input ones for slices
            without pixels).
        slice_weight: ``[n]`` in ``[0, 1]`` (0: excluded or not used).
        included: ``[n]`` bool, the slices that contributed to the final volume.
        ncc: ``[n]`` NCC of each slice with the final volume through the acquisition model (NaN:
            slice without pixels).
        timings: seconds per stage (``coarse``, ``gaussian_average``, ``registration``, ``robust``,
            ``superresolution``, ``total``).
        grid: the output grid.
        exclusion_reason: ``[n]`` why each slice is not in the volume (``None``: included):
            ``"not_used"`` (not accepted by the caller, or no pixel in its mask),
            ``"residual_outlier"`` (rejected by the robust statistics after registration),
            ``"stack_outlier"`` (also inconsistent with its stack's other slices from the start).
        coarse: the coarse alignment (``None`` when not run).
        quality: the report of :func:`~service.reconstruction.quality.quality_report` (``None`` when off).
        held_out_ncc: ``[n]`` each slice's NCC with the volume solved without its stack (NaN: not measured).
        intensity: each slice's intensity correction of the last round (``None``: not fitted).
    """

    volume: Volume
    atlas_from_voxel_final: NDArray[np.float64]
    slice_weight: NDArray[np.float64]
    included: NDArray[np.bool_]
    ncc: NDArray[np.float64]
    timings: dict[str, float] = field(default_factory=dict)
    grid: Grid | None = None
    exclusion_reason: list[str | None] = field(default_factory=list)
    coarse: CoarseAlignment | None = None
    quality: dict | None = None
    held_out_ncc: NDArray[np.float64] | None = None
    intensity: SliceIntensity | None = None


def capture(cfg: ReconstructionConfig, round_index: int, slices: SliceSet,
            coarse: CoarseAlignment | None = None) -> tuple[float, float]:
    """Trust radius (mm == deg) and volume blur (sigma, mm) of registration round ``round_index`` (1-based).

    When most slices start from their stack's pose (their own predicted poses fit the other stacks
    worse: the predictions are coarse), the first rounds follow ``cfg.capture_schedule`` (the extra
    blur added in quadrature to the forward model's in-plane blur); otherwise, and in the later
    rounds, ``cfg.registration_step_mm`` and that blur. (A wide, blurred first round would cost
    accurate starting poses dearly, hence the condition.)
    """
    base = inplane_sigma_mm(slices)
    wide = coarse is not None and np.mean(coarse.start[slices.include] != START_OWN) >= WIDE_CAPTURE_FRACTION
    if cfg.coarse_to_fine and wide and round_index - 1 < len(cfg.capture_schedule):
        step, extra = cfg.capture_schedule[round_index - 1]
        return float(step), float(np.hypot(base, extra))
    return float(cfg.registration_step_mm), base


def _register(slices: SliceSet, poses: NDArray, x: NDArray, grid: Grid, model: ForwardModel | None,
              pixel_weight: NDArray, lam: float, delta: float, support: NDArray,
              cfg: ReconstructionConfig, round_index: int = 0,
              coarse: CoarseAlignment | None = None, start: NDArray | None = None) -> tuple[NDArray, float]:
    """One registration stage: all slices at once, or fold by fold against leave-out volumes.

    Returns the registered transforms and the seconds spent re-solving leave-out volumes.
    """
    step_mm, blur_mm = capture(cfg, round_index, slices, coarse)
    kw = dict(subsample=cfg.registration_subsample, psf_points=cfg.registration_psf_points,
              max_iterations=cfg.registration_iterations, step_mm=step_mm, blur_sigma_mm=blur_mm,
              prior=start, prior_sd_mm=cfg.registration_prior_sd_mm)
    live = live_stacks(slices.stack_index, slices.include)      # a stack without an included slice is no fold
    folds = min(cfg.leave_out_folds, len(live))
    if folds < 2 or model is None:
        return register_slices(x, grid, slices, poses, **kw).atlas_from_voxel, 0.0
    fold_of_slice = np.searchsorted(live, slices.stack_index) % folds
    fold_of_pixel = fold_of_slice[slices.slice_id]
    moved = poses.copy()
    t_sr = 0.0
    for k in range(folds):                                   # a loop over <= 3 folds, not over slices
        t0 = time.perf_counter()
        xk = solve_without(model, slices.values, pixel_weight, fold_of_pixel == k, x,
                           iterations=cfg.leave_out_sr_iterations, lam=lam, delta=delta, support=support)
        t_sr += time.perf_counter() - t0
        fold = fold_of_slice == k
        moved[fold] = register_slices(xk, grid, slices, poses, active=fold, **kw).atlas_from_voxel[fold]
    return moved, t_sr


def reconstruct(slice_set: SliceSet, resolution_mm: float = 0.8, svr_iterations: int = 3,
                progress: Progress | None = None, cancel: Callable[[], bool] | None = None, *,
                bounds_mm: ArrayLike | None = None, config: ReconstructionConfig | None = None) -> ReconstructionResult:
    """Reconstruct a volume in atlas space from slices with (predicted) poses.

    Args:
        slice_set: the slices (see :meth:`SliceSet.from_stacks`); its ``atlas_from_voxel`` are the
            starting transforms.
        resolution_mm: isotropic output voxel size.
        svr_iterations: rounds of registration + robust weighting + super-resolution, after one
            round of robust weighting + super-resolution at the starting poses (0: the Gaussian
            average only).
        progress: ``progress(stage, fraction)`` called at the start of every stage and at the end.
        cancel: polled between stages; returning True raises :class:`Cancelled`.
        bounds_mm: ``[[lower], [upper]]`` field of view in atlas mm (default: the bounding box of
            the pixels at their starting positions plus ``config.margin_mm``).
        config: tuning (:class:`ReconstructionConfig`).

    Returns:
        The :class:`ReconstructionResult`, its volume the brain's compact body (:func:`compact_brain`).

    Raises:
        ValueError: if no slice is included.
        Cancelled: when ``cancel()`` returns True.
    """
    cfg = config or ReconstructionConfig()
    if slice_set.n_pixels == 0 or not slice_set.include.any():
        raise ValueError("reconstruct: no included slice has any pixel inside its mask")
    t_start = time.perf_counter()
    unbinned = slice_set                    # its pixels' extent is the default field of view
    if cfg.inplane_binning:                 # per-slice outputs keep their meaning (SliceSet.binned)
        slice_set = slice_set.binned(inplane_bin_factors(slice_set, resolution_mm, cfg.bin_below_fraction))
    timings = {"coarse": 0.0, "gaussian_average": 0.0, "registration": 0.0, "robust": 0.0, "superresolution": 0.0}
    state = {"done": 0}

    def stage(name: str) -> None:
        if cancel is not None and cancel():
            raise Cancelled(f"cancelled before {name}")
        if progress is not None:
            progress(name, state["done"] / n_stages)
        state["done"] += 1

    poses = np.array(slice_set.atlas_from_voxel, dtype=np.float64)
    n = slice_set.n_slices
    sid = slice_set.slice_id
    rounds = max(int(svr_iterations), 0)
    coarse_on = cfg.coarse_to_fine and cfg.register and rounds > 0
    n_stages = 1 + max(3 * (rounds + 1 if rounds else 0) - 1, 0) + (3 if coarse_on else 0)
    coarse = None
    if coarse_on:
        t0 = time.perf_counter()
        coarse = coarse_align(slice_set, poses, plane_x_mm=cfg.symmetry_plane_x_mm, levels_mm=cfg.stack_levels_mm,
                              sweeps=cfg.stack_sweeps, stage=stage, follow_motion_mm=cfg.stack_follow_motion_mm,
                              orders=cfg.slice_orders)
        poses = coarse.poses.copy()
        timings["coarse"] = time.perf_counter() - t0
    start = poses.copy()
    bounds = bounds_of(unbinned.positions(poses), cfg.margin_mm) if bounds_mm is None else bounds_mm
    if bounds_mm is None and coarse is not None:       # the coarse step moved the slices: not too far
        reach = bounds_of(unbinned.positions(unbinned.atlas_from_voxel), cfg.margin_mm + cfg.fov_growth_mm)
        bounds = bounds_within(bounds, reach)          # every slice moved out of reach: where they started
    grid = make_grid(resolution_mm, bounds)
    check_volume_size(grid)
    lams = list(np.geomspace(cfg.lam_first, cfg.lam, rounds)) if rounds > 1 else [cfg.lam] * rounds
    if rounds:
        lams.insert(0, cfg.lam_initial)                 # round 0: sharpen the average, no registration

    stage("gaussian average")
    t0 = time.perf_counter()
    ga = gaussian_average(slice_set, poses, grid, sigma_mm=cfg.ga_sigma_mm)
    x, support = ga.volume, ga.support
    timings["gaussian_average"] += time.perf_counter() - t0
    slice_weight = slice_set.include.astype(np.float64)
    included = slice_set.include.copy()
    model = None
    pixel_weight = slice_weight[sid].astype(np.float32)
    inlier = np.ones(slice_set.n_pixels, np.float32)        # the robust inlier probabilities of the last round
    observed, intensity = slice_set, None                    # the slices as acquired; their last correction
    poor = np.zeros(n, bool)
    restarted = np.zeros(n, bool)
    counts = slice_set.pixel_counts()             # the NCC of a slice with a few pixels at the edge says little
    judged = judged_slices(slice_set.include, counts)
    for it, lam in enumerate(lams):
        delta = default_delta(x, support, cfg.delta_fraction)
        if it > 0:
            stage(f"registration {it}/{rounds}" if cfg.register else f"round {it}/{rounds} at the starting poses")
            t0 = time.perf_counter()
            if cfg.register:
                if coarse is not None:             # a slice started from a pose that does not fit: restart it
                    restart = poor & (coarse.start == START_OWN) & ~restarted
                    poses[restart] = coarse.stack_poses[restart]
                    restarted |= restart
                moved, t_sr = _register(slice_set, poses, x, grid, model, pixel_weight, float(lam), delta,
                                        support, cfg, it, coarse, start)
                poses = anchor_frame(slice_set, poses, moved, slice_weight) if cfg.anchor_frame else moved
                timings["superresolution"] += t_sr
                timings["registration"] -= t_sr
            timings["registration"] += time.perf_counter() - t0

        stage(f"robust weighting {it}/{rounds}")
        t0 = time.perf_counter()
        model = ForwardModel(slice_set, poses, grid, psf_points=cfg.psf_points)
        simulated = model.forward(x) if cfg.robust or cfg.intensity_matching else None
        if cfg.intensity_matching:
            # every candidate slice, the excluded ones too: judged against matched slices at their own
            # intensities, a slice of another gain would stay an outlier wherever registration put it
            intensity = fit_intensity(observed, simulated, observed.values, inlier, observed.include)
            slice_set = replace(observed, values=observed.values * intensity.factor(observed))
        if cfg.robust:
            rw = robust_weights(slice_set.values - simulated, sid, n, ratio=cfg.exclude_ratio,
                                candidates=slice_set.include, tolerance=cfg.robust_tolerance)
            poor = ncc_outliers(slice_ncc(simulated, slice_set.values, sid, n), judged)
            rw.slice_weight[poor] = 0.0
            included = slice_set.include & ~rw.excluded & ~poor
            slice_weight = rw.slice_weight
            inlier = rw.pixel_weight
            pixel_weight = rw.pixel_weight * slice_weight[sid].astype(np.float32)
        timings["robust"] += time.perf_counter() - t0

        stage(f"super-resolution {it}/{rounds}")
        t0 = time.perf_counter()
        x = super_resolve(model, slice_set.values, pixel_weight, x, iterations=cfg.sr_iterations, lam=float(lam),
                          delta=delta, support=support).volume
        timings["superresolution"] += time.perf_counter() - t0

    if cancel is not None and cancel():
        raise Cancelled("cancelled before finishing")
    t0 = time.perf_counter()
    x = compact_brain(x, grid.spacing)          # the volume returned: what the quality report judges
    if model is None:
        model = ForwardModel(slice_set, poses, grid, psf_points=cfg.psf_points)
    ncc = slice_ncc(model.forward(x), slice_set.values, sid, n)
    timings["final_ncc"] = time.perf_counter() - t0
    quality, held_out = None, None
    if cfg.quality:
        t0 = time.perf_counter()
        held_out = held_out_ncc(model, slice_set.values, pixel_weight, sid,
                                held_out_groups(slice_set.stack_index, slice_set.slice_index, slice_set.include),
                                lambda w: gaussian_average(slice_set, poses, grid, sigma_mm=cfg.ga_sigma_mm,
                                                           pixel_weight=w).volume,
                                lambda sim, val: slice_ncc(sim, val, sid, n), float(lams[-1] if lams else cfg.lam),
                                default_delta(x, support, cfg.delta_fraction), support,
                                judged=observed.values, include=slice_set.include)   # as acquired: the matching saw the volume
        quality = quality_report(ncc, held_out, judged_slices(included, counts), slice_set.stack_index,
                                 judged, slice_set.slice_index, slice_set.include)
        timings["quality"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    if progress is not None:
        progress("done", 1.0)
    reasons = exclusion_reasons(slice_set.include, included, None if coarse is None else coarse.fit.inlier)
    return ReconstructionResult(Volume(x.astype(np.float32), grid.affine.copy()), poses,
                                np.where(included, slice_weight, 0.0), included, ncc, timings, grid, reasons, coarse,
                                quality, held_out, intensity)
