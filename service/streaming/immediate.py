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
* **Two estimates of one pose.** The network's answer and the placement's prediction are weighed
  by their expected errors (the received slices' spread about the placement,
  :func:`placement_spread_mm`: the stack's motion and the network's error in one figure): their
  weighted Fréchet mean is answered, expected as the network's answer was (the mean's own figure
  would trust two estimates whose errors are neither Gaussian nor independent). At a stack's ends
  (little brain in the slice) the network's answer for a lone slice can be tens of millimetres
  off: where it lies further from the prediction than :data:`OUTLIER_SIGMAS` times their combined
  expected error, the prediction alone is answered, expected as far off as the stack's spread and
  never nearer than the answer it overrules.

Example (a slice whose network answer, expected within 2 mm, lies 40 mm from where its stack puts
it, the stack's slices within 3 mm of their placement: the placement's pose is answered; 1 mm off,
the two are weighed 9 : 4 in the network answer's favour):
    >>> pose, predicted = np.eye(4), np.eye(4)
    >>> pose[0, 3] = 40.0
    >>> chosen, expected = with_placement(pose, 2.0, predicted, 3.0)
    >>> float(chosen[0, 3]), expected
    (0.0, 3.0)
    >>> pose[0, 3] = 1.0
    >>> chosen, expected = with_placement(pose, 2.0, predicted, 3.0)
    >>> round(float(chosen[0, 3]), 3), expected
    (0.692, 2.0)
    >>> with_placement(pose, float("nan"), predicted, 3.0)[0] is pose     # no expected error: left alone
    True
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from service.geometry import anchors, se3

UNDECIDED_TWIN_CHANCE = 0.5
"""The chance that a slice answered before its stack decided its branch sits on its mirror twin: a
slice alone cannot tell (docs/realtime.md gives the share measured on simulated acquisitions)."""
MIN_WEIGHED_MM = 0.5
"""The smallest expected error an estimate is weighed by (a spread of 0 would trust the placement alone)."""
OUTLIER_SIGMAS = 1.0
"""How many combined expected errors the network's answer may lie from the placement's prediction
before the prediction alone is answered (:func:`with_placement`)."""


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


def with_placement(pose: NDArray[np.float64], expected_mm: float, predicted: NDArray[np.float64],
                   spread_mm: float) -> tuple[NDArray[np.float64], float]:
    """The network's ``pose`` weighed with the placement's ``predicted`` pose (weights the inverse
    squares of ``expected_mm`` and the stack's ``spread_mm``), expected as the network's; where the
    two lie more than :data:`OUTLIER_SIGMAS` combined errors apart, the prediction alone, expected as
    far off as ``spread_mm`` and never nearer than the network answer it overrules (a sudden move of
    the fetus makes the network right and the placement wrong, and one slice cannot tell which)."""
    if not (np.isfinite(expected_mm) and np.isfinite(spread_mm)):
        return pose, float(expected_mm)                # no figure to weigh by (a degenerate answer)
    if float(anchors.ed(pose, predicted)) > OUTLIER_SIGMAS * float(np.hypot(expected_mm, spread_mm)):
        return predicted.copy(), float(max(spread_mm, expected_mm))
    weights = 1.0 / np.maximum([expected_mm, spread_mm], MIN_WEIGHED_MM) ** 2
    return se3.frechet_mean(np.stack([pose, predicted]), weights), float(expected_mm)
