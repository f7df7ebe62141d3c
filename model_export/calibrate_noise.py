"""Calibrate how a model's expected errors grow with the noise of its inputs (``noise_error``).

The MC spread measures what the network is unsure of on the slices it learnt from. A stack noisier
than those (a low-field scanner's, coarse pixels that keep their noise) is posed worse than its
spread says, mostly by a larger turn and shift of the whole request, which no stage sees: its
slices agree with each other. The service adds that error in quadrature to every slice's expected error,
``slope x max(0, input_noise - onset)`` mm from its stack's input noise
(:func:`~service.preprocess.noise.noise_error_mm`), so that a noisy stack's slices are accepted as
a clean stack's are: by what their errors are likely to be.

Simulated 3-stack acquisitions of the validation volumes at a ladder of Rician noise levels and two
pixel sizes (:data:`NOISE_LADDER`, :data:`PIXELS_MM`; a 128 mm field of view, 3 mm slices) go
through the very pipeline the server runs, with the model's other calibrations and without this
one. Each stack's slices are grouped by its input noise (:data:`BIN_EDGES`). ``onset`` and ``slope``
are those that bring every group's median of ``E.D. / sqrt(expected^2 + s^2)`` (each slice's ``s``
from its own stack's noise) nearest what that median is in the clean stacks (below
:data:`CLEAN_NOISE`): a noisy stack's slices then stand to their expected errors as clean ones do
(:func:`fit_hinge`). The median, not the RMS, because the RMS of a group is set by its few slices
on their twin or far off, which the accept flags judge by other means. The report also gives each
group's own missing error (:func:`missing_error`), the ``s`` it alone would ask for, and each
group's median ratio with the fitted hinge: where the error grows faster than a hinge, some groups
are left a little over-trusted and others under-trusted. The offset is shared by a request's
slices, so an acquisition, not a slice, is the unit of evidence; requests that mix noisy and clean
stacks are not simulated.

    svrnet-train calibrate-noise service/models/default/model.onnx [--no-write]   # needs the atlas data
"""

from __future__ import annotations

from copy import copy
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from model_export.acquisitions import SimulatedStack, simulate_acquisition
from model_export.evaluate_acquisitions import MIN_MASK_PIXELS, Scored, run_acquisition, score

NOISE_LADDER = (0.03, 0.06, 0.09, 0.12, 0.15, 0.18)
"""Rician noise SDs, as shares of the bright end, the calibration simulates (the training draws up to 0.08)."""
PIXELS_MM = (1.0, 1.6)
"""In-plane pixel sizes: finer pixels than the network's 1.25 mm average part of the noise away, coarser keep it."""
LEVELS = ("mild", "moderate", "jumps")
PER_VOLUME = 2
"""Acquisitions per validation volume, noise level, pixel size and motion level: 180 in all, 30 per
noise level (the shipped models' calibrations; about 12 minutes on 2 cores)."""
FOV_MM = 128.0
"""The simulated acquisitions' field of view (mm), whatever their pixel size."""
BIN_EDGES = (0.0, 0.06, 0.09, 0.11, 0.13, 0.15, 0.17, 1.0)
"""Groups of stacks by their input noise."""
CLEAN_NOISE = 0.06
"""Stacks below this input noise are as clean as the calibration of the spread (the reference groups)."""
MIN_GROUP_SLICES = 100
"""A group with fewer slices takes no part in the fit."""
NOISE_FLAGS = ("noise_error",)
"""What :func:`calibrate` chooses, under the name of the model's metadata the service reads."""


def measure(estimator, volumes: list, per_volume: int = PER_VOLUME, seed: int = 7,  # noqa: ANN001
            levels: tuple[str, ...] = LEVELS) -> dict[str, NDArray]:
    """Per slice with brain, over the ladder: its E.D. against the truth (``ed``), its expected error
    (``expected``, inf where it has none) and its stack's input noise (``input_noise``); the
    estimator's own ``noise_error`` switched off while they are measured, and its ``frame_error``,
    which is calibrated after it (``calibrate-frame``)."""
    estimator = copy(estimator)                  # the caller's keeps its calibration
    estimator.info = replace(estimator.info, noise_error=None, frame_error=None)
    scored = Scored()
    for level in levels:
        for noise in NOISE_LADDER:
            for pixel_mm in PIXELS_MM:
                for a, vol in enumerate(volumes * per_volume):
                    stacks = acquire(vol, np.random.default_rng([seed, a]), level, pixel_mm=pixel_mm, noise=noise)
                    (predictions,), prepared, truth = run_acquisition(stacks, estimator)
                    score(predictions, prepared, truth, stacks, estimator.info.symmetry_plane_x_mm, scored)
    keep = scored.array("mask_pixels") >= MIN_MASK_PIXELS
    return {k: scored.array(k)[keep] for k in ("ed", "expected", "input_noise")}


def acquire(volume, rng: np.random.Generator, level: str, pixel_mm: float = 1.0, thickness_mm: float = 3.0,  # noqa: ANN001
            gap_mm: float = 3.0, noise: float = 0.03, **more: float) -> list[SimulatedStack]:
    """One simulated 3-stack acquisition of an atlas ``volume`` as another scanner writes it: ``pixel_mm``
    pixels over a :data:`FOV_MM` field of view, slices ``thickness_mm`` thick ``gap_mm`` apart, Rician
    ``noise`` (a share of the bright end); ``more``: other :func:`simulate_acquisition` keywords (``bias``)."""
    return simulate_acquisition(volume.image, volume.mask, volume.affine, rng, level, size=int(round(FOV_MM / pixel_mm)),
                                pixel_mm=pixel_mm, thickness_mm=thickness_mm, gap_mm=gap_mm, noise=noise, **more)


def median_ratio(ed: NDArray, expected: NDArray, extra_mm: float = 0.0) -> float:
    """The median of ``ed / sqrt(expected^2 + extra_mm^2)``.

    Example:
        >>> median_ratio(np.array([3.0, 5.0, 8.0]), np.array([4.0, 4.0, 4.0]), 3.0)
        1.0
    """
    return float(np.median(ed / np.hypot(expected, extra_mm)))


def missing_error(ed: NDArray, expected: NDArray, target: float, top_mm: float = 30.0) -> float:
    """The error ``s`` (mm) that brings :func:`median_ratio` down to ``target`` (0 where it is there already).

    Example (errors twice their expected 3 mm; the clean ratio 1):
        >>> round(missing_error(np.full(9, 6.0), np.full(9, 3.0), 1.0), 2)      # sqrt(36 - 9)
        5.2
    """
    if median_ratio(ed, expected) <= target:
        return 0.0
    lo, hi = 0.0, top_mm
    for _ in range(50):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if median_ratio(ed, expected, mid) > target else (lo, mid)
    return (lo + hi) / 2


def fit_hinge(noise: NDArray, ed: NDArray, expected: NDArray, groups: list[NDArray], target: float,
              slopes: NDArray = np.arange(0.0, 150.1, 1.0), onsets: NDArray | None = None) -> tuple[float, float]:
    """``(onset, slope)`` of ``slope x max(0, noise - onset)`` that brings each group of slices
    (boolean masks ``groups``) nearest :func:`median_ratio` ``target``, each slice with its own
    stack's ``noise`` (or any level the error grows with): the sum over groups of their slices
    times the squared log of their median ratio over the target, smallest (the onset on
    ``onsets``, default a 0.005 grid from 0, the slope on ``slopes``).

    Example (slices of noise 0.05 as trusted as they should be, those of 0.15 lacking 3 mm):
        >>> noise = np.repeat([0.05, 0.15], 4); x = np.full(8, 4.0)
        >>> e = np.r_[np.full(4, 4.0), np.full(4, 5.0)]
        >>> onset, slope = fit_hinge(noise, e, x, [noise < 0.1, noise > 0.1], 1.0, np.arange(0.0, 101.0, 5.0))
        >>> round(float(slope * (0.15 - onset)), 1)
        3.0
    """
    best = (np.inf, 0.0, 0.0)
    for onset in np.arange(0.0, float(noise.max()) + 1e-9, 0.005) if onsets is None else onsets:
        hinge = np.maximum(noise - onset, 0.0)
        for slope in slopes:
            scaled = ed / np.hypot(expected, slope * hinge)
            cost = sum(float(g.sum()) * np.log(float(np.median(scaled[g])) / target) ** 2 for g in groups)
            if cost < best[0] - 1e-12:
                best = (cost, float(onset), float(slope))
            if slope > 0 and not hinge.any():
                break
    return best[1], best[2]


def calibrate_hinge(level: NDArray, ed: NDArray, expected: NDArray, edges: tuple[float, ...], clean_below: float,
                    key: str, reference: str, slopes: NDArray = np.arange(0.0, 150.1, 1.0),
                    onsets: NDArray | None = None) -> tuple[float, float, float, list[dict]]:
    """``(onset, slope, target, groups)`` of a hinge error on ``level`` (a stack's input noise, a
    request's network error): the slices grouped by their level between ``edges`` (a group of under
    :data:`MIN_GROUP_SLICES` left out), the target the median ratio of E.D. to expected error of the
    slices under ``clean_below``, the hinge :func:`fit_hinge`'s; each group's median level under
    ``key``, its slices, median E.D. and expected error, median ratio before and after the fit and
    its own missing error (:func:`missing_error`). Slices without an expected error or a level are
    left out. :class:`ValueError` where the reference (``reference``: what its slices are) or two
    groups are missing.

    Example (slices of level 1 as trusted as they should be, those of level 3 lacking 4 mm):
        >>> level = np.repeat([1.0, 3.0], 120); ed = np.r_[np.full(120, 3.0), np.full(120, 5.0)]
        >>> onset, slope, target, groups = calibrate_hinge(level, ed, np.full(240, 3.0), (0, 2, 4), 2.0, "level",
        ...                                                "slices of level 1", np.arange(0.0, 5.0, 0.5), np.arange(0.0, 3.5, 0.5))
        >>> round(slope * (3.0 - onset), 1), target, [g["slices"] for g in groups]
        (4.0, 1.0, [120, 120])
    """
    have = np.isfinite(expected) & np.isfinite(level)
    level, ed, expected = level[have], ed[have], expected[have]
    clean = level < clean_below
    if clean.sum() < MIN_GROUP_SLICES:
        raise ValueError(f"{int(clean.sum())} slices of {reference}: the clean reference needs {MIN_GROUP_SLICES}")
    target = median_ratio(ed[clean], expected[clean])
    groups, masks = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        g = (level >= lo) & (level < hi)
        if g.sum() < MIN_GROUP_SLICES:
            continue
        masks.append(g)
        groups.append({key: float(np.median(level[g])), "slices": int(g.sum()),
                       "ed_median_mm": float(np.median(ed[g])), "expected_median_mm": float(np.median(expected[g])),
                       "median_ratio": median_ratio(ed[g], expected[g]),
                       "missing_mm": missing_error(ed[g], expected[g], target)})
    if len(groups) < 2:
        raise ValueError("the slices fill fewer than two groups of their level: nothing to fit a growth to")
    onset, slope = fit_hinge(level, ed, expected, masks, target, slopes, onsets)
    for g, m in zip(groups, masks):
        g["median_ratio_after"] = median_ratio(ed[m], np.hypot(expected[m], slope * np.maximum(level[m] - onset, 0.0)))
    return onset, slope, target, groups


def hinge_table(groups: list[dict], key: str, onset: float, slope: float, header: str, level_label: str,
                level_format: str) -> str:
    """:func:`calibrate_hinge`'s groups and fit as a Markdown table under ``header``, the groups' levels
    in a column ``level_label`` written with ``level_format``.

    Example:
        >>> g = {"noise": 0.12, "slices": 9, "ed_median_mm": 3.0, "expected_median_mm": 2.5, "median_ratio": 1.2,
        ...      "missing_mm": 1.6, "median_ratio_after": 1.0}
        >>> hinge_table([g], "noise", 0.1, 50.0, "fit", "input noise", "{:.3f}").splitlines()[-1]
        '| 0.120 | 9 | 3.00 mm | 2.50 mm | 1.20 | 1.60 mm | 1.00 mm | 1.00 |'
    """
    lines = [header, "", f"| {level_label} (median) | slices | median E.D. | median expected | median ratio "
             "| its missing error | the fit's | median ratio with it |", "|---|---|---|---|---|---|---|---|"]
    for g in groups:
        fitted = slope * max(g[key] - onset, 0.0)
        lines.append(f"| {level_format.format(g[key])} | {g['slices']} | {g['ed_median_mm']:.2f} mm "
                     f"| {g['expected_median_mm']:.2f} mm | {g['median_ratio']:.2f} | {g['missing_mm']:.2f} mm "
                     f"| {fitted:.2f} mm | {g['median_ratio_after']:.2f} |")
    return "\n".join(lines)


def calibrate(columns: dict[str, NDArray]) -> dict:
    """``noise_error`` (onset, slope) from :func:`measure`'s columns, and each group's figures
    (:func:`calibrate_hinge`)."""
    onset, slope, target, groups = calibrate_hinge(
        columns["input_noise"], columns["ed"], columns["expected"], BIN_EDGES, CLEAN_NOISE, "noise",
        f"stacks under input noise {CLEAN_NOISE}; measure with the noise ladder's lowest levels")
    return {"noise_error": [onset, slope], "clean_median_ratio": target, "groups": groups}


def noise_metadata(result: dict) -> dict[str, str]:
    """The calibrated ``noise_error`` as the model's metadata value.

    Example:
        >>> noise_metadata({"noise_error": [0.1, 41.234]})
        {'noise_error': '0.1,41.23'}
    """
    onset, slope = result["noise_error"]
    return {"noise_error": f"{onset:.4g},{slope:.4g}"}


def markdown(result: dict) -> str:
    """The groups and the fit as a Markdown table (:func:`hinge_table`)."""
    onset, slope = result["noise_error"]
    return hinge_table(result["groups"], "noise", onset, slope,
                       f"noise_error: onset {onset:.3f}, slope {slope:.1f} mm per unit of input noise "
                       f"(clean median E.D. / expected {result['clean_median_ratio']:.2f})", "input noise", "{:.3f}")
