"""The expected error of each refined pose a job returns (``refined_expected_error_mm``).

A ``/v1/predict`` slice's ``expected_error_mm`` describes the network's pose. A job moves most
slices to where its volume puts them, and their errors change in kind: a slice in the volume, or
one the job placed beside it, shares the volume's frame error (where the atlas frame and midline
steps leave the brain: the same for every slice of one brain) and adds a little of its own; a slice
the job did not place keeps its starting pose's error. What the job sees of each
slice tells them apart, and flags a slice whose pose disagrees with the volume:

* its role: in the volume, placed by its stack's motion or registered to the volume
  (:mod:`~service.reconstruction.left_out`), or left at its starting pose;
* its NCC with the volume simulated at its final pose, against the median of the slices in the
  volume by the same measure (:attr:`~service.reconstruction.left_out.LeftOutPlacement.ncc`): a placed slice
  that falls short of it sits elsewhere than the volume says. A large brain section tells more
  than a cap (:data:`~service.reconstruction.left_out.MIN_AREA_MM2`), which fits the volume less
  well even where it belongs;
* for a slice in the volume, its prediction's expected error: a slice the network found hard (a
  cap, a section through the skull base) is harder to register too.

A placed slice's expected E.D. is the root of the sum of the squares of :data:`FRAME_MM`,
:data:`BESIDE_MM` for a slice placed beside the volume, :data:`PREDICTED_SHARE` of a slice in the
volume's predicted error, and :data:`SHORTFALL_MM` per unit its NCC ratio falls below
:data:`NCC_RATIO`. The constants are least squares on the squared E.D. of simulated jobs
(``model_export/experiments/refined_errors.py``; the calibration is in docs/reconstruction.md).
A slice the job did not place keeps its starting pose's expected error, or more where it disagrees
with the volume. Where the job's stacks do not predict each other
(:func:`~service.reconstruction.quality.incoherent`), or cannot be judged so (one stack), or the
frame steps did not move the poses, the constants do not hold: no slice's expected error falls
below its starting pose's.

Example (a slice in the volume, one that fits it badly, one left out at its prediction's 9 mm,
one not posed):
    >>> import numpy as np
    >>> role = np.array([IN_VOLUME, IN_VOLUME, LEFT_OUT, LEFT_OUT])
    >>> e = refined_expected_errors(role, np.array([0.95, 0.40, 0.5, np.nan]), np.full(4, 1000.0),
    ...                             np.array([3.0, 3.0, 9.0, np.nan]), held_out_ncc=0.9)
    >>> bool(e[0] < 3.0 < e[1]), float(e[2]), bool(np.isnan(e[3]))
    (True, 9.0, True)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.reconstruction.left_out import MIN_AREA_MM2
from service.reconstruction.quality import MIN_HELD_OUT_NCC, incoherent

IN_VOLUME, PLACED_BY_STACK_MOTION, PLACED_BY_VOLUME, LEFT_OUT = 0, 1, 2, 3
"""A slice's role in the job (:func:`roles`)."""

FRAME_MM = 1.5
"""The volume's frame error every placed slice shares, with its own scatter in the volume."""
BESIDE_MM = 2.0
"""What a slice placed beside the volume (by its stack's motion or registered to it) adds."""
PREDICTED_SHARE = 0.5
"""The share of its predicted pose's expected error a slice in the volume keeps."""
NCC_RATIO = 0.95
"""A placed slice whose NCC with the volume stays above this fraction of the median of the slices in
the volume agrees with it."""
SHORTFALL_MM = {True: 21.0, False: 12.0}
"""mm per unit the NCC ratio falls below :data:`NCC_RATIO`, for a large brain section
(>= :data:`~service.reconstruction.left_out.MIN_AREA_MM2`) and for a smaller one."""


def roles(included: ArrayLike, placed_by_stack_motion: ArrayLike, placed_by_volume: ArrayLike) -> NDArray[np.int64]:
    """``[n]`` each slice's role (:data:`IN_VOLUME` ... :data:`LEFT_OUT`) from the job's flags.

    Example:
        >>> roles([True, False, False, False], [False, True, False, False], [False, False, True, False]).tolist()
        [0, 1, 2, 3]
    """
    return np.select([np.asarray(included, bool), np.asarray(placed_by_stack_motion, bool),
                      np.asarray(placed_by_volume, bool)], [IN_VOLUME, PLACED_BY_STACK_MOTION, PLACED_BY_VOLUME],
                     LEFT_OUT)


def refined_expected_errors(role: ArrayLike, ncc: ArrayLike, area_mm2: ArrayLike, predicted_mm: ArrayLike, *,
                            held_out_ncc: float | None, framed: bool = True,
                            stack_held_out_ncc: ArrayLike | None = None) -> NDArray[np.float64]:
    """``[n]`` the expected E.D. (mm) of each refined pose (module docstring).

    Args:
        role: ``[n]`` each slice's role (:func:`roles`).
        ncc: ``[n]`` each slice's NCC with the volume at its final pose (NaN: not measured).
        area_mm2: ``[n]`` its brain section's area.
        predicted_mm: ``[n]`` its starting pose's ``expected_error_mm`` (NaN: none known; a left-out
            slice's stays NaN, a placed slice's is the volume's alone).
        held_out_ncc: the job's leave-one-stack-out median NCC (None: not measured, one stack).
        framed: the atlas-frame and midline steps moved the poses (what the constants were fitted
            after). Where they did not, or the stacks do not predict each other (``held_out_ncc``
            incoherent or not measured), no slice's expected error falls below its starting pose's,
            and a slice without one has none.
        stack_held_out_ncc: ``[n]`` the leave-one-stack-out median NCC of each slice's stack (NaN:
            not measured): a stack the others do not predict (a stack of another fetus, another
            contrast) is treated so alone, whatever the job's median.
    """
    role = np.asarray(role, np.int64)
    c, predicted = np.asarray(ncc, np.float64), np.asarray(predicted_mm, np.float64)
    inside = role == IN_VOLUME
    median = float(np.nanmedian(c[inside])) if np.isfinite(c[inside]).any() else float("nan")
    ratio = np.nan_to_num(c / median, nan=NCC_RATIO) if median > 0 else np.full(len(c), NCC_RATIO)
    large = np.asarray(area_mm2, np.float64) >= MIN_AREA_MM2
    shortfall = np.maximum(NCC_RATIO - ratio, 0.0) * np.where(large, SHORTFALL_MM[True], SHORTFALL_MM[False])
    beside = np.where(inside, 0.0, BESIDE_MM)
    share = np.where(inside, PREDICTED_SHARE * np.nan_to_num(predicted, nan=0.0), 0.0)  # none known: a client's
    out = np.sqrt(FRAME_MM ** 2 + beside ** 2 + share ** 2 + shortfall ** 2)
    # No lower than the starting pose's error (none where that is unknown): a slice the job did not
    # place (more where it disagrees with the volume: an excluded slice may have been registered
    # before the job left it out), every slice where the constants do not hold, and the slices of a
    # stack the others do not predict.
    floored = np.where(np.isfinite(predicted), np.fmax(out, predicted), np.nan)
    if not framed or held_out_ncc is None or incoherent(held_out_ncc):
        return floored
    stack = np.full(len(role), np.nan) if stack_held_out_ncc is None else np.asarray(stack_held_out_ncc, np.float64)
    return np.where((role == LEFT_OUT) | (np.isfinite(stack) & (stack < MIN_HELD_OUT_NCC)), floored, out)


def refined_summary(role: ArrayLike, refined_mm: ArrayLike, starting_mm: ArrayLike) -> dict:
    """The job report's ``refined_poses``: over the posed slices (a refined expected error known), how
    many the job placed and how; the median expected error of the refined poses and of the starting
    ones, over the slices that have both (the refined poses' over every posed slice where no starting
    error is known; None for none).

    Example:
        >>> refined_summary([IN_VOLUME, IN_VOLUME, PLACED_BY_STACK_MOTION, LEFT_OUT, LEFT_OUT],
        ...                 [2.1, 2.5, 2.5, 12.0, np.nan], [3.0, 4.0, 9.0, 12.0, np.nan])
        {'posed': 4, 'in_volume': 2, 'placed_by_stack_motion': 1, 'placed_by_volume': 0, 'median_expected_error_mm': 2.5, 'median_starting_expected_error_mm': 6.5}
    """
    role, refined, starting = (np.asarray(x) for x in (role, refined_mm, starting_mm))
    posed = np.isfinite(refined.astype(np.float64))
    known = posed & np.isfinite(starting.astype(np.float64))
    compared = known if known.any() else posed                     # both medians over the same slices
    median = lambda x: round(float(np.median(x)), 3) if len(x) else None  # noqa: E731
    return {"posed": int(posed.sum()), **{name: int(np.sum(posed & (role == r))) for name, r in
                                          (("in_volume", IN_VOLUME), ("placed_by_stack_motion", PLACED_BY_STACK_MOTION),
                                           ("placed_by_volume", PLACED_BY_VOLUME))},
            "median_expected_error_mm": median(refined[compared]),
            "median_starting_expected_error_mm": median(starting[known])}
