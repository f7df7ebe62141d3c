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
one of ``X``'s voxel axes in the scanner -- which is where the other stacks hold it, while ``A_X``
itself is turned far from them (up to 180 degrees). Only the turns are compared: the plane of ``F``
is free (reversed voxels reflect about the stack's middle, a lost sign about its first voxel), and
the fetus may move between stacks.

Two stacks either have one handedness (turned by at most :data:`SAME_TURN_DEG`), are mirror images
(one of them reflected lies within :data:`MIRROR_TURN_DEG` of the other, :data:`MIRROR_MARGIN`
times nearer than as it is), or say nothing (the fetus turned between them). Within each group of stacks so related,
each stack is given a handedness that satisfies as many of these pairs as can be; the stacks of
the smaller side are the mirrored ones, and where two sides are even (two stacks) both are, since
the request cannot tell which. A reflection across a plane near the head's own mid-sagittal plane
turns the symmetric brain by little: the stack shows the brain nearly as it was, and is not found.

The same placement is that of an ordinary stack whose own slices decided its left-right branch
wrongly by a wide margin (its whole twin is its reflection across its middle slice): that stack is
flagged too, rightly, since its slices lie on the twin of where the others put them.

Example (a stack and its copy whose slices were written in reverse order):
    >>> from service.geometry import se3
    >>> placement = se3.exp(np.array([0.3, -0.2, 0.1, 5.0, -3.0, 2.0]))
    >>> flip = np.diag([1.0, 1.0, -1.0, 1.0]); flip[2, 3] = 27.0
    >>> reflected = twin.mirror() @ placement @ flip        # where the stage places the reversed copy
    >>> relation(placement, reflected, np.eye(3), np.eye(3)), relation(placement, placement, np.eye(3), np.eye(3))
    ('mirrored', 'same')
"""

from __future__ import annotations

from collections.abc import Callable
from itertools import combinations, product

import numpy as np
from numpy.typing import NDArray

from service.geometry import twin

SAME_TURN_DEG = 30.0
"""Two stacks' placements turned against each other by at most this hold the fetus with one
handedness (at jump motion two stacks of one acquisition lie up to 16 deg apart; their positions
may lie further apart than their turn says, which handedness does not care for)."""
MIRROR_TURN_DEG = 20.0
"""A stack is another's mirror image only where, reflected, it lies within this of it: tighter than
:data:`SAME_TURN_DEG`, since a fetus turned far between two stacks can fall near one of a stack's
reflections by chance, while a reflected file's stack lies near its reflection at every motion
level of the held-out acquisitions (the rates: docs/consistency.md)."""
MIRROR_MARGIN = 3.0
"""A stack is another's mirror image where, reflected, it lies within :data:`SAME_TURN_DEG` of it and
as it is at least this many times as far (as a stack's own branch is overruled by the request:
``stage.OVERRULE_MARGIN``)."""
MAX_STACKS = 12
"""Handedness is assigned by trying every assignment of a group of related stacks (``2 ** stacks``)
up to this many stacks; a larger group is searched from each stack's propagated handedness, one
stack turned over at a time while that satisfies more pairs (:func:`_local_best`)."""
MIRROR = twin.mirror()[:3, :3]
"""The atlas's left-right reflection, its linear part (:func:`~service.geometry.twin.mirror`)."""


def _turn_deg(a: NDArray, b: NDArray) -> float:
    """The angle (deg) of the rotation from the ``3 x 3`` rotation ``a`` to ``b``."""
    cos = (np.trace(b @ a.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def relation(a: NDArray, b: NDArray, axes_a: NDArray, axes_b: NDArray) -> str:
    """How two stacks' placements ``a`` and ``b`` (``atlas_from_scanner``) relate: ``"same"`` (one
    handedness: turned by at most :data:`SAME_TURN_DEG`), ``"mirrored"`` (one of them reflected along
    one of its voxel axes ``axes_*``, ``3 x 3`` in the scanner, lies within :data:`MIRROR_TURN_DEG` of
    the other, and as it is :data:`MIRROR_MARGIN` times as far) or ``"neither"``. Only the turns count: a
    reflection's plane offset is free, and the fetus may move between stacks."""
    ra, rb = np.asarray(a, np.float64)[:3, :3], np.asarray(b, np.float64)[:3, :3]
    apart = _turn_deg(ra, rb)
    if apart <= SAME_TURN_DEG:
        return "same"
    best = np.inf
    for axes in (axes_a, axes_b):             # either stack may be the reflected one: try it on a's side
        for axis in range(3):
            u = axes[:, axis] / np.linalg.norm(axes[:, axis])
            best = min(best, _turn_deg(MIRROR @ ra @ (np.eye(3) - 2.0 * np.outer(u, u)), rb))
    return "mirrored" if best <= MIRROR_TURN_DEG and apart >= MIRROR_MARGIN * best else "neither"


def mirrored_stacks(placements: list[NDArray | None], axes: list[NDArray]) -> list[bool]:
    """Which stacks of a request hold the mirror image of what their file says (module docstring).

    Args:
        placements: each stack's ``atlas_from_scanner`` where the stage decided its branch by its own
            slices, else None (the stack takes no part).
        axes: each stack's voxel axes ``3 x 3`` in the scanner (its affine's columns).

    Returns:
        Per stack, whether it is taken for mirrored: within its group of related stacks, on the
        smaller side of the handedness that satisfies the most pairs of stacks that agree or are
        mirror images (both sides where they are even; a stack related to no other has no side). A
        group with no mirror-image pair has none.

    Example (three stacks, the first the mirror image of two that agree):
        >>> from service.geometry import se3
        >>> a = se3.exp(np.array([0.3, -0.2, 0.1, 5.0, -3.0, 2.0]))
        >>> flip = np.diag([1.0, 1.0, -1.0, 1.0])
        >>> mirrored_stacks([twin.mirror() @ a @ flip, a, a], [np.eye(3)] * 3)
        [True, False, False]
        >>> mirrored_stacks([twin.mirror() @ a @ flip, a, None], [np.eye(3)] * 3)
        [True, True, False]
    """
    which = [i for i, p in enumerate(placements) if p is not None]
    flagged = [False] * len(placements)
    pairs = {}
    for i, j in combinations(which, 2):
        kind = relation(placements[i], placements[j], axes[i], axes[j])
        if kind != "neither":
            pairs[i, j] = kind
    for group in _groups(pairs):
        within = {pair: kind for pair, kind in pairs.items() if pair[0] in group}
        if "mirrored" in within.values():
            for i in _smaller_sides(group, within):
                flagged[i] = True
    return flagged


def _groups(pairs: dict[tuple[int, int], str]) -> list[list[int]]:
    """The stacks joined by ``pairs`` (agreeing or mirror images), in groups that no pair links: each
    group's handedness is its own (a group of stacks between which the fetus moved says nothing of
    another's)."""
    group: dict[int, int] = {}
    for i, j in pairs:
        a, b = group.setdefault(i, i), group.setdefault(j, j)
        if a != b:
            group = {k: (a if g == b else g) for k, g in group.items()}
    return [sorted(k for k, g in group.items() if g == root) for root in sorted(set(group.values()))]


def _smaller_sides(group: list[int], pairs: dict[tuple[int, int], str],
                   exhaustive_up_to: int = MAX_STACKS) -> set[int]:
    """The stacks of ``group`` on the smaller side of each handedness that satisfies the most of its
    ``pairs`` (both sides where they are even): every handedness tried up to ``exhaustive_up_to``
    stacks, the local optima of :func:`_local_best` beyond."""
    def score(hand: dict[int, int]) -> int:
        return sum((hand[i] == hand[j]) == (kind == "same") for (i, j), kind in pairs.items())

    if len(group) <= exhaustive_up_to:
        hands = [dict(zip(group, (1, *signs))) for signs in product((1, -1), repeat=len(group) - 1)]
    else:
        hands = _local_best(group, pairs, score)
    scores = [score(hand) for hand in hands]
    out: set[int] = set()
    for hand in (h for h, sc in zip(hands, scores) if sc == max(scores)):
        plus = [i for i in group if hand[i] == 1]
        minus = [i for i in group if hand[i] == -1]
        out.update(minus if len(minus) < len(plus) else plus if len(plus) < len(minus) else plus + minus)
    return out


def _local_best(group: list[int], pairs: dict[tuple[int, int], str],
                score: Callable[[dict[int, int]], int]) -> list[dict[int, int]]:
    """Handedness assignments of a large ``group``: from each stack, its handedness carried to the
    others along the ``pairs`` (breadth first: a stack takes its first related neighbour's, the
    same or the opposite), then one stack at a time turned over while that satisfies more pairs.
    Where the pairs agree with each other (every request but one with a stack the fetus left
    mid-way) the first assignment satisfies them all, and it is the one answer, as the exhaustive
    search finds; the search is linear in the stacks and quadratic in the pairs."""
    links: dict[int, list[tuple[int, int]]] = {i: [] for i in group}
    for (i, j), kind in pairs.items():
        sign = 1 if kind == "same" else -1
        links[i].append((j, sign))
        links[j].append((i, sign))
    found = []
    for root in group:
        hand, queue = {root: 1}, [root]
        for i in queue:
            for j, sign in links[i]:
                if j not in hand:
                    hand[j] = hand[i] * sign
                    queue.append(j)
        best = score(hand)
        while True:
            turned = [{**hand, i: -hand[i]} for i in group]
            gains = [score(h) for h in turned]
            if max(gains) <= best:
                break
            best, hand = max(gains), turned[int(np.argmax(gains))]
        found.append({i: hand[i] * hand[group[0]] for i in group})      # the first stack at +1, as above
    return [dict(t) for t in {tuple(sorted(h.items())) for h in found}]


__all__ = ["MAX_STACKS", "MIRROR_MARGIN", "MIRROR_TURN_DEG", "SAME_TURN_DEG", "mirrored_stacks", "relation"]
