"""The pose a streamed slice gets the moment it arrives, and how far off it may be.

A slice alone is the network's answer for that slice (MC statistics of one slice). What the stream
knows beyond it is its stack's model, once the stack stage has run on the slices received so far
(:meth:`~service.streaming.session.StreamSession.firm_up`): the stack's placement
(``atlas_from_scanner``) puts the new slice where the stack was on average, and its left-right branch
is decided. Two things follow for the immediate answer:

* **The branch.** Before the stack decides it, nothing tells a slice from its mirror twin (the atlas
  space is left-right symmetric): the truth is the answered pose or its twin with even chances, so
  the expected squared error gains half the squared distance to the twin
  (:data:`UNDECIDED_TWIN_CHANCE`). Once decided, the slice takes the twin nearer to the placement's
  prediction.
* **The network's outliers.** At a stack's ends (little brain in the slice) the network's answer
  for a lone slice can be tens of millimetres off where the stack puts it. Where the answer lies
  further from the placement's prediction than :data:`OUTLIER_SIGMAS` times their combined expected
  error, the prediction is answered instead, expected as far off as the received slices lie from
  the placement (:func:`placement_spread_mm`: the received slices' network answers about it, the
  stack's motion and the network's error in one figure), and never nearer than the answer it
  overrules.

Example (a slice whose network answer, expected within 2 mm, lies 40 mm from where its stack puts
it, the stack's slices within 3 mm of their placement: the placement's pose is answered):
    >>> pose, predicted = np.eye(4), np.eye(4)
    >>> pose[0, 3] = 40.0
    >>> chosen, expected = nearer_of(pose, 2.0, predicted, 3.0)
    >>> float(chosen[0, 3]), expected
    (0.0, 3.0)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from service.geometry import anchors

UNDECIDED_TWIN_CHANCE = 0.5
"""The chance that a slice answered before its stack decided its branch sits on its mirror twin: a
slice alone cannot tell (docs/realtime.md gives the share measured on simulated acquisitions)."""
OUTLIER_SIGMAS = 1.0
"""How many combined expected errors the network's answer may lie from the placement's prediction
before the prediction is answered instead (:func:`nearer_of`)."""


def placement_spread_mm(network_poses: NDArray[np.float64], atlas_from_scanner: NDArray[np.float64],
                        network_from_scanner: NDArray[np.float64], usable: NDArray[np.bool_]) -> float | None:
    """RMS E.D. (mm) between the network's poses ``[n, 4, 4]`` (network frame -> atlas, each on the
    branch its stack took) of the ``usable`` slices and where the stack's placement
    ``atlas_from_scanner`` puts them: how far a slice the placement predicts lies from it, the
    stack's motion and the network's own error both in it (None without a usable slice).

    Example (three slices 0, 3 and 4 mm from the placement along x):
        >>> poses = np.stack([np.eye(4)] * 3); poses[:, 0, 3] = [0.0, 3.0, 4.0]
        >>> round(placement_spread_mm(poses, np.eye(4), np.stack([np.eye(4)] * 3), np.ones(3, bool)), 3)
        2.887
    """
    if not np.any(usable):
        return None
    predicted = atlas_from_scanner @ np.linalg.inv(network_from_scanner[usable])
    return float(np.sqrt(np.mean(np.square(anchors.ed(network_poses[usable], predicted)))))


def nearer_of(pose: NDArray[np.float64], expected_mm: float, predicted: NDArray[np.float64],
              spread_mm: float) -> tuple[NDArray[np.float64], float]:
    """The network's ``pose`` with its ``expected_mm``, or the placement's ``predicted`` pose where the
    two lie more than :data:`OUTLIER_SIGMAS` combined errors apart, expected as far off as the stack's
    ``spread_mm`` and never nearer than the network answer it overrules (a sudden move of the fetus
    makes the network right and the placement wrong, and one slice cannot tell which)."""
    if float(anchors.ed(pose, predicted)) > OUTLIER_SIGMAS * float(np.hypot(expected_mm, spread_mm)):
        return predicted.copy(), float(max(spread_mm, expected_mm))
    return pose, float(expected_mm)
