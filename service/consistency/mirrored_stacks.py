"""Stacks whose voxels are the mirror image of what their file's header says, found by the request.

A file whose voxels were reversed along one axis while its affine was not (slices written in the
reverse order, rows flipped by a converter), or whose affine lost the sign of one axis, is a
reflection of the scan it holds. Each of its slices still looks like a slice of a brain, and the
atlas brain is symmetric, so the network places each slice as well as ever -- on the twin of where
it lies -- and the stack stage finds one rigid stack on its twin branch, decided by its own slices
with a wide margin. Nothing in the stack alone can tell: it is the stack of the mirror-image fetus.

The request can. Its stacks share the scanner frame, and a stack's placement
(:attr:`~service.consistency.stack_fit.StackFit.atlas_from_scanner`) is where the fetus was while it
was acquired. A reflected stack ``X`` of placement ``A_X`` holds the fetus at ``M A_X F`` -- ``M``
the atlas's left-right reflection (:func:`~service.geometry.twin.mirror`), ``F`` the reflection of
``X``'s voxel axis in the scanner -- which is where the other stacks hold it, while ``A_X`` itself
lies far from them (a rotation near 180 degrees). The plane of ``F`` is free (reversed voxels
reflect about the stack's middle, a lost sign about its first voxel): the comparison takes the
shift along the axis that brings the two nearest.

Two stacks either agree (placements within :data:`~service.consistency.stack_fit.REQUEST_AGREEMENT_MM`
of each other), are mirror images (one of them reflected agrees with the other, and they lie
:data:`MIRROR_MARGIN` times as far apart as that), or say nothing (the fetus moved between them).
Each stack is given a handedness that satisfies as many of these pairs as can be; the stacks of
the smaller side are the mirrored ones, and where two sides are even (two stacks) both are, since
the request cannot tell which.

Example (a stack and its copy whose slices were written in reverse order):
    >>> from service.geometry import se3
    >>> placement = se3.exp(np.array([0.3, -0.2, 0.1, 5.0, -3.0, 2.0]))
    >>> affine = np.diag([1.2, 1.2, 3.0, 1.0])
    >>> frames = np.stack([affine @ se3.exp(np.array([0, 0, 0, 0, 0, 3.0 * k])) for k in range(10)])
    >>> flip = np.diag([1.0, 1.0, -1.0, 1.0]); flip[2, 3] = 9 * 3.0
    >>> reflected = twin.mirror() @ placement @ flip        # where the stage places the reversed copy
    >>> relation(placement, reflected, frames, frames, affine[:3, :3], affine[:3, :3])
    'mirrored'
    >>> relation(placement, placement, frames, frames, affine[:3, :3], affine[:3, :3])
    'same'
"""

from __future__ import annotations

from itertools import combinations, product

import numpy as np
from numpy.typing import NDArray

from service.consistency.stack_fit import REQUEST_AGREEMENT_MM
from service.geometry import anchors, twin

MIRROR_MARGIN = 3.0
"""A stack is another's mirror image where, reflected, it lies within
:data:`~service.consistency.stack_fit.REQUEST_AGREEMENT_MM` of it and as it is at least this many
times as far (as a stack's own branch is overruled by the request: ``stage.OVERRULE_MARGIN``)."""
MAX_STACKS = 12
"""Handedness is assigned by trying every assignment (``2 ** stacks``); more stacks than this are
not checked."""


def _points(placement: NDArray, frames: NDArray) -> NDArray[np.float64]:
    """``[n, 3, 3]`` the anchor points of the slice frames ``frames`` (scanner) placed by ``placement``."""
    return anchors.encode(placement @ frames).reshape(-1, 3, 3)


def _distance(a: NDArray, b: NDArray) -> float:
    """Mean E.D. (mm) between two sets of anchor points ``[n, 3, 3]``."""
    return float(np.linalg.norm(a - b, axis=-1).mean())


def relation(a: NDArray, b: NDArray, frames_a: NDArray, frames_b: NDArray, axes_a: NDArray, axes_b: NDArray,
             plane_x_mm: float = twin.DEFAULT_PLANE_X_MM) -> str:
    """How two stacks' placements ``a`` and ``b`` (``atlas_from_scanner``) relate: ``"same"`` (one fetus
    position, within :data:`~service.consistency.stack_fit.REQUEST_AGREEMENT_MM`), ``"mirrored"``
    (one of them reflected along one of its voxel axes lies there, and they are :data:`MIRROR_MARGIN`
    times as far apart as that) or ``"neither"``. Distances are the mean E.D. of both stacks' slice
    frames (``frames_*``: ``[n, 4, 4]`` network frame -> scanner mm) placed by each; ``axes_*``: each
    stack's ``3 x 3`` voxel axes in the scanner (its affine's columns)."""
    frames = np.concatenate([frames_a, frames_b])
    target = _points(b, frames)
    apart = _distance(_points(a, frames), target)
    if apart <= REQUEST_AGREEMENT_MM:
        return "same"
    mirrored = twin.mirror(plane_x_mm) @ a
    best = np.inf
    for axes in (axes_a, axes_b):             # either stack may be the reflected one: try it on a's side
        for axis in range(3):
            u = axes[:, axis] / np.linalg.norm(axes[:, axis])
            flip = np.eye(4)
            flip[:3, :3] -= 2.0 * np.outer(u, u)               # the reflection across a plane through 0
            placed = _points(mirrored @ flip, frames)
            w = mirrored[:3, :3] @ flip[:3, :3] @ u            # where a move of that plane moves them
            shift = float(((target - placed) @ w).mean())      # the plane's best offset
            best = min(best, _distance(placed + shift * w, target))
    return "mirrored" if best <= REQUEST_AGREEMENT_MM and apart >= MIRROR_MARGIN * best else "neither"


def mirrored_stacks(placements: list[NDArray | None], frames: list[NDArray], axes: list[NDArray],
                    plane_x_mm: float = twin.DEFAULT_PLANE_X_MM) -> list[bool]:
    """Which stacks of a request hold the mirror image of what their file says (module docstring).

    Args:
        placements: each stack's ``atlas_from_scanner`` where the stage decided its branch by its own
            slices, else None (the stack takes no part).
        frames: each stack's slice frames ``[n, 4, 4]`` (network frame -> scanner mm).
        axes: each stack's voxel axes ``3 x 3`` in the scanner (its affine's columns).
        plane_x_mm: the atlas's symmetry plane.

    Returns:
        Per stack, whether it is taken for mirrored: on the smaller side of the handedness that
        satisfies the most pairs of stacks that agree or are mirror images (both sides where they
        are even; a stack related to no other has no side). A request with no mirror-image pair has
        none.

    Example (three stacks, the first the mirror image of two that agree):
        >>> from service.geometry import se3
        >>> a = se3.exp(np.array([0.3, -0.2, 0.1, 5.0, -3.0, 2.0]))
        >>> frames = np.stack([se3.exp(np.array([0, 0, 0, 0, 0, 3.0 * k])) for k in range(10)])
        >>> flip = np.diag([1.0, 1.0, -1.0, 1.0])
        >>> mirrored_stacks([twin.mirror() @ a @ flip, a, a], [frames] * 3, [np.eye(3)] * 3)
        [True, False, False]
        >>> mirrored_stacks([twin.mirror() @ a @ flip, a, None], [frames] * 3, [np.eye(3)] * 3)
        [True, True, False]
    """
    which = [i for i, p in enumerate(placements) if p is not None]
    flagged = [False] * len(placements)
    if not 2 <= len(which) <= MAX_STACKS:
        return flagged
    pairs = {}
    for i, j in combinations(which, 2):
        kind = relation(placements[i], placements[j], frames[i], frames[j], axes[i], axes[j], plane_x_mm)
        if kind != "neither":
            pairs[i, j] = kind
    if "mirrored" not in pairs.values():
        return flagged
    best, ties = -1, []
    for signs in product((1, -1), repeat=len(which) - 1):    # the first stack's handedness fixed at +1
        hand = dict(zip(which, (1, *signs)))
        score = sum((hand[i] == hand[j]) == (kind == "same") for (i, j), kind in pairs.items())
        if score > best:
            best, ties = score, [hand]
        elif score == best:
            ties.append(hand)
    related = {k for pair in pairs for k in pair}            # a stack in no pair has no side
    for hand in ties:                         # every assignment as good as the best: the smaller side of each
        plus = [i for i in related if hand[i] == 1]
        minus = [i for i in related if hand[i] == -1]
        for side in ((minus,) if len(minus) < len(plus) else (plus,) if len(plus) < len(minus) else (plus, minus)):
            for i in side:
                flagged[i] = True
    return flagged


__all__ = ["MIRROR_MARGIN", "mirrored_stacks", "relation"]
