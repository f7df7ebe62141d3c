"""The image stage of a request (:func:`refine_where_stacks_cross`): the settled stacks' poses refined
where their slices cross, which of them together and which against fixed partners, and what the
refinement leaves of each slice's expected error (:func:`placement_floor_mm`).

Example (the floor of two stacks placed to 4 and 1.5 mm per coordinate):
    >>> from types import SimpleNamespace as N
    >>> placed = [N(pooled=None, fit=N(placement_sd_mm=sd)) for sd in (4.0, 1.5)]
    >>> round(placement_floor_mm(placed), 2)
    2.6
"""

from __future__ import annotations

import numpy as np

from service.consistency.image_refinement import refine, smooth_ahead
from service.consistency.refined_errors import agreed, expected_after, relative_mismatch
from service.consistency.slice_images import SampledStack, StackImages
from service.consistency.stage import ImageConsistency, StackPoses, branch_set
from service.pipeline.prepare import PreparedStack


def refine_where_stacks_cross(prepared: list[PreparedStack], outs: list[StackPoses], proper: list[np.ndarray],
                              smoothed: list[dict[float, SampledStack]] | None = None) -> None:
    """Refine the poses of the request's settled stacks where their slices cross
    (:func:`~service.consistency.image_refinement.refine`), in place; each such stack's
    ``image_consistency`` says what it did. A stack takes part when the stage found it consistent and
    its left-right branch is decided (by its own slices or by the request): a stack that may be the
    mirror image of the others would pull them towards it. Of their slices, those with a ``proper`` network pose that the stage did not
    flag as inconsistent take part.

    The stacks whose branch is known (``StackFit.branch_known``: decided by their own slices, or by
    the request where they sit with its stacks) are refined together first (when two or more are); a
    stack whose branch the request decided but that fits it on neither branch is then refined against
    them as fixed partners, and its slices keep at least the stage's expected error: it is the less
    certain, and a stack whose localisation went wrong (a mask that runs on into the fetal body)
    would otherwise pull the others its way, or be pulled into a false agreement with them.

    ``smoothed``: per stack of the request, its smoothed images made ahead (:func:`smooth_images_ahead`);
    otherwise they are made here, once for both steps."""
    take = [i for i, o in enumerate(outs) if branch_set(o) and not o.apart]
    if len(take) < 2:
        return
    own = [i for i in take if outs[i].fit.branch_known]
    store = None if smoothed is None else dict(enumerate(smoothed))
    if len(own) < 2 or len(own) == len(take):
        _refine_stacks(prepared, outs, proper, take, [], store)
        return
    store = {i: {} for i in take} if store is None else store          # smoothed once for both steps
    _refine_stacks(prepared, outs, proper, own, [], store)
    _refine_stacks(prepared, outs, proper, [i for i in take if i not in own], own, store)


def placement_floor_mm(outs: list[StackPoses]) -> float:
    """The expected E.D. below which no returned pose of stacks the image stage refined together
    (``outs``) lies (:func:`~service.pipeline.unseen_errors.add_unseen_errors` applies it last):
    that of the best-placed stack's placement in the atlas (its pooled placement's standard error where the request's stacks were
    pooled, else its own; ``sqrt(3)`` x the error per coordinate). The images relate the slices to
    each other, not to the atlas: two stacks that agree where they cross are placed no better than
    the better of the two. The floor matters where the stacks' placements are poor, as in real
    requests whose network poses scatter widely about their motion models (the placements and
    floors measured: docs/consistency.md).

    Example (two stacks placed to 4 and 1.5 mm per coordinate: the better one's, 2.6 mm):
        >>> from types import SimpleNamespace as N
        >>> outs = [N(pooled=N(placement_sd_mm=4.0), fit=None), N(pooled=None, fit=N(placement_sd_mm=1.5))]
        >>> round(placement_floor_mm(outs), 2)
        2.6
    """
    sds = [o.pooled.placement_sd_mm if o.pooled is not None else
           (o.fit.placement_sd_mm if o.fit is not None else np.nan) for o in outs]
    known = [sd for sd in sds if np.isfinite(sd)]
    return float(np.sqrt(3.0) * min(known)) if known else 0.0


def stack_images(prepared: PreparedStack, active: np.ndarray | None = None, fixed: bool = False) -> StackImages:
    """A prepared stack's slices as the image stage sees them; ``active`` (default: all) the slices
    that take part."""
    s = prepared.slices
    active = np.ones(len(s.images), bool) if active is None else active
    return StackImages(s.images, s.masks, s.pixel_mm, prepared.prepared.input_from_network(), active, fixed=fixed)


def smooth_images_ahead(prepared: list[PreparedStack]) -> list[dict[float, SampledStack]]:
    """Every image-stage pass's smoothed images of every stack of the request
    (:func:`~service.consistency.image_refinement.smooth_ahead`): they need neither the poses nor the
    stage's verdicts, so :func:`~service.pipeline.predict.predict_from_estimates` makes them beside the stack stage."""
    return smooth_ahead([stack_images(p) for p in prepared])


def _refine_stacks(prepared: list[PreparedStack], outs: list[StackPoses], proper: list[np.ndarray],
                   moving: list[int], partners: list[int], smoothed: dict[int, dict] | None = None) -> None:
    """:func:`refine` the stacks ``moving`` (indices into ``prepared``) with the stacks ``partners`` as
    fixed partners; sets the moving stacks' poses, expected errors (with partners, or where the
    refinement left the slices disagreeing, :func:`~service.consistency.refined_errors.agreed`:
    never below the stage's) and ``image_consistency`` (with the :func:`placement_floor_mm` of the
    stacks refined). Where no slice of theirs crosses another's (stacks of one orientation), nothing
    changes: the images checked nothing.
    ``smoothed``: per stack (its index in ``prepared``), :func:`refine`'s store of its smoothed images."""
    which = moving + partners
    images = [stack_images(prepared[i], proper[i] & ~outs[i].inconsistent, fixed=i in partners) for i in which]
    expected = [outs[i].expected_error_mm if outs[i].expected_error_mm is not None
                else np.full(len(outs[i].poses), np.nan) for i in which]
    ref = refine(images, [outs[i].poses for i in which], expected,
                 smoothed=None if smoothed is None else [smoothed[i] for i in which])
    if ref.pairs == 0:              # no slice crosses another stack's (parallel stacks): nothing was checked,
        return                      # and the stacks keep what the stack stage said of them
    relative = relative_mismatch(ref.mismatch)
    after = expected_after(expected, relative, ref.spread_mm)
    floor = placement_floor_mm([outs[i] for i in which])
    for j, i in enumerate(moving):
        outs[i].poses = ref.poses[j]
        if outs[i].expected_error_mm is not None:
            outs[i].expected_error_mm = (np.fmax(after[j], expected[j]) if partners or not agreed(ref.cost_after)
                                         else after[j])
        moved = ref.moved_mm[j][images[j].active]
        outs[i].image_consistency = ImageConsistency(len(which), ref.pairs, int(images[j].active.sum()),
                                                     float(np.median(moved)) if len(moved) else 0.0,
                                                     float(ref.cost_before), float(ref.cost_after),
                                                     relative[j], expected[j], ref.spread_mm[j], floor)
