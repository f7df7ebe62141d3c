"""Calibrate how a request's frame error grows with the network's error on its slices (``frame_error``).

A request's slices can agree with each other and the request still lie turned and shifted in the
atlas frame as a whole: the model's expected-error floor holds that common error as the benchmarks'
acquisitions have it. It is larger where the network is less sure of the request's slices, the
stacks' ``network_error_mm`` (their network poses' error about their motion models) higher: on
whole-uterus requests without masks, on real scans (:mod:`service.consistency.frame_error`). The
service adds ``slope x max(0, sigma - onset)`` mm in quadrature to every slice's expected error,
``sigma`` the request's network error (:func:`~service.consistency.frame_error.request_network_error_mm`).

The calibration runs, through the very pipeline the server runs and without this term, simulated
3-stack acquisitions of the validation volumes at the motion levels the accept flags were
calibrated on (:data:`LEVELS`), and whole-uterus requests of three stacks of the same brains
planned about the head (:func:`~model_export.localiser.pose_accuracy.validation_cases`, mild
motion), each sent without masks (the localiser's) and with the atlas's brain masks. Each slice
is grouped by its request's network error (:data:`SIGMA_EDGES`). ``onset`` and ``slope`` are
those that bring every group's median of ``E.D. / sqrt(expected^2 + s^2)`` nearest what it is on
the requests under :data:`CLEAN_SIGMA_MM` (the acquisitions the floor was fitted on), by
:func:`~model_export.calibrate_noise.fit_hinge`, as the noise error is fitted. The median, not the
RMS: the RMS of a group is set by its few slices on their twin or far off.

    svrnet-train calibrate-frame service/models/default/model.onnx [--no-write]   # needs the atlas data
"""

from __future__ import annotations

from copy import copy
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from model_export.acquisitions import simulate_acquisition
from model_export.calibrate_noise import calibrate_hinge, hinge_table
from model_export.evaluate_acquisitions import MIN_MASK_PIXELS, Scored, run_acquisition, score

LEVELS = ("mild", "moderate", "jumps")
PER_VOLUME = 2
"""Acquisitions per validation volume and motion level."""
SCENES = 10
"""Whole-uterus requests (of three stacks; each sent without masks and with the atlas's brain masks)."""
SCENE_VARIANTS = ("localiser", "brain")
SIGMA_EDGES = (0.0, 11.0, 13.0, 15.0, 18.0, 22.0, 1e3)
"""Groups of slices by their request's network error (mm)."""
CLEAN_SIGMA_MM = 13.0
"""Requests under this network error are as the acquisitions the expected-error floor was fitted on
(the reference groups: about three in four of them)."""
ONSETS_MM = np.arange(8.0, 30.01, 0.5)
SLOPES = np.arange(0.0, 1.501, 0.02)
FRAME_FLAGS = ("frame_error",)
"""What :func:`calibrate` chooses, under the name of the model's metadata the service reads."""


def measure(estimator, volumes: list, per_volume: int = PER_VOLUME, seed: int = 11, scenes: int = SCENES,  # noqa: ANN001
            scene_seed: int = 2_400_000) -> dict[str, NDArray]:
    """Per slice with brain: its E.D. against the truth (``ed``), its expected error (``expected``, inf
    where it has none) and its request's network error (``sigma``, NaN where no stack had a fit); the
    estimator's own ``frame_error`` switched off."""
    from model_export.localiser.pose_accuracy import score_scene, validation_cases
    from service.preprocess.localise import default_localiser

    estimator = copy(estimator)                  # the caller's keeps its calibration
    estimator.info = replace(estimator.info, frame_error=None)
    rows: dict[str, list] = {k: [] for k in ("ed", "expected", "sigma")}

    def add(ed: NDArray, expected: NDArray, sigma: float) -> None:          # one request's slices
        rows["ed"].append(ed)
        rows["expected"].append(np.where(np.isfinite(expected), expected, np.inf))
        rows["sigma"].append(np.full(len(ed), sigma))

    for level in LEVELS:
        for a, vol in enumerate(volumes * per_volume):
            stacks = simulate_acquisition(vol.image, vol.mask, vol.affine, np.random.default_rng([seed, a]), level)
            (predictions,), prepared, truth = run_acquisition(stacks, estimator)
            scored = Scored()
            score(predictions, prepared, truth, stacks, estimator.info.symmetry_plane_x_mm, scored)
            keep = scored.array("mask_pixels") >= MIN_MASK_PIXELS
            add(scored.array("ed")[keep], scored.array("expected")[keep], predictions[0].request_network_error_mm)
    localiser = default_localiser()
    for case in validation_cases(scenes, scene_seed, 3, motion="mild", planning="orthogonal"):
        for variant in SCENE_VARIANTS:
            got = score_scene(case, variant, estimator, localiser if variant == "localiser" else None)
            posed = np.isfinite(got["ed"])
            add(got["ed"][posed], got["expected"][posed], float(got["network_error"]))
    return {k: np.concatenate(v) for k, v in rows.items()}


def calibrate(columns: dict[str, NDArray]) -> dict:
    """``frame_error`` (onset, slope) from :func:`measure`'s columns, and each group's figures
    (:func:`~model_export.calibrate_noise.calibrate_hinge`)."""
    onset, slope, target, groups = calibrate_hinge(
        columns["sigma"], columns["ed"], columns["expected"], SIGMA_EDGES, CLEAN_SIGMA_MM, "sigma_mm",
        f"requests under a network error of {CLEAN_SIGMA_MM} mm; measure with acquisitions", SLOPES, ONSETS_MM)
    return {"frame_error": [onset, slope], "clean_median_ratio": target, "groups": groups}


def frame_metadata(result: dict) -> dict[str, str]:
    """The calibrated ``frame_error`` as the model's metadata value.

    Example:
        >>> frame_metadata({"frame_error": [13.0, 0.4812]})
        {'frame_error': '13,0.4812'}
    """
    onset, slope = result["frame_error"]
    return {"frame_error": f"{onset:.4g},{slope:.4g}"}


def markdown(result: dict) -> str:
    """The groups and the fit as a Markdown table (:func:`~model_export.calibrate_noise.hinge_table`)."""
    onset, slope = result["frame_error"]
    return hinge_table(result["groups"], "sigma_mm", onset, slope,
                       f"frame_error: onset {onset:.1f} mm, slope {slope:.2f} mm per mm of the request's network error "
                       f"(reference median E.D. / expected {result['clean_median_ratio']:.2f})",
                       "request's network error", "{:.1f} mm")
