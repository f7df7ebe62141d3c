"""How good a reconstruction is, judged without ground truth: what a user (and our benchmarks on
real scans) can trust.

Two measures, both from the acquired slices themselves:

* **agreement**: each slice against the volume simulated at its refined pose through the
  acquisition model (its NCC). A slice that sits where it was acquired looks like the volume there.
  Reported: the median over the judged slices and the fraction above :data:`GOOD_NCC`.
* **leave one stack out**: the volume solved without one stack's pixels, each slice of that stack
  against it. The solve starts from the Gaussian average of the other stacks, not from the full
  volume: a few conjugate-gradient iterations from the full volume keep the left-out stack's imprint
  wherever no other stack reaches, and slices piled where only their own stack lies then predict
  themselves. A volume that only echoes its own slices, or stacks that disagree, score well on
  agreement and badly here: it measures whether the stacks predict each other. The left-out
  slices are judged as acquired: their intensity matching (:mod:`~service.reconstruction.intensity`)
  was fitted to a volume that held them, and NCC needs no gain. Reported: the median
  per stack and over all slices, and whether that median reaches :data:`MIN_HELD_OUT_NCC`
  (``coherent``: false for a volume that is no coherent brain).
* **leave alternate slices out**, with one stack: its slices agree with a volume made of themselves
  wherever they are put, so agreement says nothing; the volume solved without the even slices
  judges them, and the one without the odd slices judges those. A slice sitting where it was
  acquired lies between its neighbours, and the volume they make predicts it; slices placed
  anywhere else are predicted by nothing. ``coherent`` then says whether that median reaches
  :data:`MIN_ALTERNATE_NCC`.

A slice is judged when it has at least :data:`MIN_PIXEL_FRACTION` of the median slice's pixels (an
edge slice of a few pixels says little) and was used: for agreement, in the volume; for leaving
a stack out, given to the job, so that a path that drops slices is judged on them too.

Example (a volume that predicts its slices perfectly, and one slice that does not):
    >>> import numpy as np
    >>> ncc = np.array([0.95, 0.9, 0.92, 0.1]); held = np.array([0.9, 0.85, 0.88, 0.05])
    >>> r = quality_report(ncc, held, np.ones(4, bool), np.array([0, 0, 1, 1]))
    >>> r["median_ncc"], r["fraction_ncc_above_0_7"], r["leave_one_stack_out"]["per_stack_median_ncc"]
    (0.91, 0.75, [0.875, 0.465])
    >>> r["coherent"]                     # the stacks predict each other: leaving one out, 0.865
    True
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from service.reconstruction.forward import ForwardModel
from service.reconstruction.superresolution import solve_without

MIN_HELD_OUT_NCC = 0.5
"""Below this leave-one-stack-out median NCC the stacks do not predict each other: the volume is no
coherent brain, and neither the frame steps nor a user should trust it: good jobs score well above
it, and the midline step turns an incoherent volume the wrong way (the scores measured:
docs/reports/reconstruction-experiments.md, "The figures behind the job's constants")."""

MIN_ALTERNATE_NCC = MIN_HELD_OUT_NCC
"""Below this leave-alternate-slices-out median NCC a single stack's slices do not predict each other
(the same 0.5; docs/reconstruction.md gives what a good and a scrambled stack score)."""

GOOD_NCC = 0.7
MIN_PIXEL_FRACTION = 0.2
HELD_OUT_ITERATIONS = 8
"""Conjugate-gradient iterations of each leave-one-stack-out solve, from the other stacks' average."""


def judged_slices(use: NDArray, pixel_counts: NDArray) -> NDArray[np.bool_]:
    """The slices whose NCC says something: used, with enough pixels (see the module)."""
    use = np.asarray(use, bool)
    counts = np.asarray(pixel_counts, np.float64)
    if not use.any():
        return use
    return use & (counts >= MIN_PIXEL_FRACTION * np.median(counts[use]))


def live_stacks(stack_index: NDArray, include: NDArray | None = None) -> NDArray[np.int64]:
    """The stacks with an ``include``-d slice (default: every stack): those a volume can be made of.

    Example:
        >>> live_stacks(np.array([0, 0, 1, 2]), np.array([True, False, False, True])).tolist()
        [0, 2]
    """
    stack_index = np.asarray(stack_index, np.int64)
    return np.unique(stack_index if include is None else stack_index[np.asarray(include, bool)])


def held_out_groups(stack_index: NDArray, slice_index: NDArray, include: NDArray | None = None) -> NDArray[np.int64]:
    """The groups :func:`held_out_ncc` leaves out in turn: the stacks, or with one stack that holds an
    ``include``-d slice its even and its odd slices (see the module; a stack none of whose slices is
    included is no group: left out, it would leave the volume as it is, and the others' volume empty).

    Example:
        >>> held_out_groups(np.array([0, 0, 1]), np.array([0, 1, 0])).tolist(), held_out_groups(np.zeros(4, int), np.arange(4)).tolist()
        ([0, 0, 1], [0, 1, 0, 1])
        >>> held_out_groups(np.array([0, 0, 1]), np.array([0, 1, 0]), np.array([True, True, False])).tolist()
        [0, 1, 0]
    """
    stack_index = np.asarray(stack_index, np.int64)
    return stack_index if len(live_stacks(stack_index, include)) > 1 else np.asarray(slice_index, np.int64) % 2


def held_out_ncc(model: ForwardModel, values: NDArray, pixel_weight: NDArray, slice_id: NDArray,
                 stack_index: NDArray, start: Callable[[NDArray], NDArray],
                 ncc: Callable[[NDArray, NDArray], NDArray], lam: float, delta: float, support: NDArray | None,
                 iterations: int = HELD_OUT_ITERATIONS, judged: NDArray | None = None,
                 include: NDArray | None = None) -> NDArray[np.float64]:
    """``[n]``: each slice's NCC against the volume solved without its stack's pixels (NaN where
    the stack is the only one, or a group without an ``include``-d slice; ``stack_index`` may be any
    grouping, :func:`held_out_groups`).
    ``start(weights)`` gives the volume the solve starts from, given the pixel weights without the
    stack (the other stacks' Gaussian average); ``ncc(simulated, values)`` gives the per-slice NCC of
    pixel vectors; ``judged``: the pixel values the left-out slices are judged by (default
    ``values``, which the solve uses: a caller that matched them to a volume holding those slices
    judges them as acquired)."""
    n = len(stack_index)
    out = np.full(n, np.nan)
    stacks = live_stacks(stack_index, include)
    if len(stacks) < 2:
        return out
    stack_of_pixel = np.asarray(stack_index)[slice_id]
    for s in stacks:                                    # a loop over the stacks, not the slices
        left_out = stack_of_pixel == s
        x0 = start(np.where(left_out, np.float32(0.0), pixel_weight))
        xs = solve_without(model, values, pixel_weight, left_out, x0, iterations=iterations, lam=lam,
                           delta=delta, support=support)
        mine = stack_index == s
        out[mine] = ncc(model.forward(xs), values if judged is None else judged)[mine]
    return out


def incoherent(held_out_ncc: float | None, minimum: float = MIN_HELD_OUT_NCC) -> bool:
    """Whether a job's stacks do not predict each other (leave-one-stack-out median NCC under
    :data:`MIN_HELD_OUT_NCC`; None: not measured, e.g. one stack): no frame step trusts its volume,
    and the report says so (``coherent``).

    Example:
        >>> incoherent(0.42), incoherent(0.9), incoherent(None)
        (True, False, False)
    """
    return held_out_ncc is not None and held_out_ncc < minimum


def _median(x: NDArray) -> float | None:
    x = np.asarray(x, np.float64)
    x = x[np.isfinite(x)]
    return round(float(np.median(x)), 4) if x.size else None


def quality_report(ncc: NDArray, held_out: NDArray, judged: NDArray, stack_index: NDArray,
                   held_out_judged: NDArray | None = None, slice_index: NDArray | None = None,
                   include: NDArray | None = None) -> dict:
    """The ``quality`` object of a job's report (see the module): agreement over the ``judged``
    slices, leaving a stack out over ``held_out_judged`` (default: the same slices). With one stack
    holding an ``include``-d slice, ``held_out`` holds each slice's NCC with its alternate slices
    left out (:func:`held_out_groups` of ``slice_index``), reported as ``leave_alternate_slices_out``."""
    judged = np.asarray(judged, bool)
    held_judged = judged if held_out_judged is None else np.asarray(held_out_judged, bool)
    c = np.asarray(ncc, np.float64)[judged]
    c = c[np.isfinite(c)]
    h = np.asarray(held_out, np.float64)
    stacks = np.unique(stack_index)
    held_median = _median(h[held_judged])
    held = {"median_ncc": held_median, "slices": int(np.isfinite(h[held_judged]).sum())}
    alone = len(live_stacks(stack_index, include)) == 1 and slice_index is not None
    minimum = MIN_ALTERNATE_NCC if alone else MIN_HELD_OUT_NCC
    report = {"judged_slices": int(judged.sum()),
              "coherent": None if held_median is None else not incoherent(held_median, minimum),
              "median_ncc": _median(c),
              "fraction_ncc_above_0_7": round(float(np.mean(c > GOOD_NCC)), 4) if c.size else None}
    if not alone:
        return {**report, "leave_one_stack_out": {
            **held, "per_stack_median_ncc": [_median(h[held_judged & (stack_index == s)]) for s in stacks]}}
    halves = held_out_groups(stack_index, slice_index, include)
    return {**report, "leave_one_stack_out": {"median_ncc": None, "slices": 0,
                                              "per_stack_median_ncc": [None] * len(stacks)},
            "leave_alternate_slices_out": {
                **held, "even_odd_median_ncc": [_median(h[held_judged & (halves == p)]) for p in (0, 1)]}}


def exclusion_reasons(include: NDArray, included: NDArray, stack_inlier: NDArray | None) -> list[str | None]:
    """Per slice: ``None`` (in the volume), ``"not_used"``, ``"stack_outlier"`` or ``"residual_outlier"``.

    Example:
        >>> exclusion_reasons(np.array([1, 1, 1, 0], bool), np.array([1, 0, 0, 0], bool),
        ...                   np.array([1, 1, 0, 0], bool))
        [None, 'residual_outlier', 'stack_outlier', 'not_used']
    """
    inlier = np.ones(len(include), bool) if stack_inlier is None else np.asarray(stack_inlier, bool)
    return [None if inc else "not_used" if not use else "residual_outlier" if ok else "stack_outlier"
            for use, inc, ok in zip(np.asarray(include, bool).tolist(), np.asarray(included, bool).tolist(),
                                    inlier.tolist())]


def slice_ncc(simulated: NDArray, values: NDArray, slice_id: NDArray, n_slices: int) -> NDArray[np.float64]:
    """Per-slice normalised cross-correlation ``[n]`` of two pixel vectors (NaN for slices without pixels)."""
    sid = np.asarray(slice_id)
    cnt = np.bincount(sid, minlength=n_slices).astype(np.float64)
    a = np.asarray(simulated, np.float64)
    b = np.asarray(values, np.float64)
    ac = a - (np.bincount(sid, a, n_slices) / np.maximum(cnt, 1))[sid]
    bc = b - (np.bincount(sid, b, n_slices) / np.maximum(cnt, 1))[sid]
    num = np.bincount(sid, ac * bc, n_slices)
    den = np.sqrt(np.bincount(sid, ac * ac, n_slices) * np.bincount(sid, bc * bc, n_slices))
    out = np.full(n_slices, np.nan)
    ok = (cnt > 0) & (den > 0)
    out[ok] = num[ok] / den[ok]
    out[(cnt > 0) & ~(den > 0)] = 0.0
    return out
