"""The pose a streamed slice gets the moment it arrives, and how far off it may be.

A slice alone is the network's answer for that slice (MC statistics of one slice). What the stream
knows beyond it is its stack's model, once the stack stage has run on the slices received so far
(:meth:`~service.streaming.session.StreamSession.firm_up`): the stack's placement
(``atlas_from_scanner``) puts the new slice where the stack was on average, and its left-right branch
is decided. Two things follow for the immediate answer:

* **The branch.** Before the stack decides it, nothing tells a slice from its mirror twin (the atlas
  space is left-right symmetric): the truth is the answered pose or its twin with even chances, so
  the expected squared error gains half the squared distance to the twin
  (:data:`~service.geometry.twin.UNDECIDED_TWIN_CHANCE`). Once decided, the slice takes the twin nearer to the placement's
  prediction.
* **Two estimates of one pose.** The network's answer and the placement's prediction are weighed
  by their expected errors. The prediction's (:func:`placement_error_mm`) is what the stack stage
  knows: how far off its own poses of the stack's slices are expected to be (the placement's
  error, most of it at mild motion), and how far the latest received slices lie from the
  placement (the fetus's motion now, doubled: a new slice is where the latest were, and the stage's
  motion fit is smooth). Their weighted Fréchet mean is answered, expected at
  :data:`SHARED_ERROR_FACTOR` times the error of the mean of two independent estimates (the two
  share errors: the placement was fitted to the network's answers). A lone slice's network answer
  can be tens of millimetres off (little brain in it, at a stack's ends): where it lies further
  from the prediction than :data:`OUTLIER_SIGMAS` times their combined expected error, the
  prediction alone is answered, expected as far off as the placement's error and never nearer
  than the answer it overrules.

Example (a slice whose network answer, expected within 2 mm, lies 40 mm from where its stack puts
it, the placement expected within 3 mm: the placement's pose is answered; 1 mm off, the two are
weighed 9 : 4 in the network answer's favour and expected at 1.41 x 1.66 mm):
    >>> pose, predicted = np.eye(4), np.eye(4)
    >>> pose[0, 3] = 40.0
    >>> chosen, expected = with_placement(pose, 2.0, predicted, 3.0)
    >>> float(chosen[0, 3]), expected
    (0.0, 3.0)
    >>> pose[0, 3] = 1.0
    >>> chosen, expected = with_placement(pose, 2.0, predicted, 3.0)
    >>> round(float(chosen[0, 3]), 3), round(expected, 2)
    (0.692, 2.35)
    >>> with_placement(pose, float("nan"), predicted, 3.0)[0] is pose     # no expected error: left alone
    True
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from service.geometry import anchors, se3

MIN_WEIGHED_MM = 0.5
"""The smallest expected error an estimate is weighed by (an error of 0 would trust one estimate alone)."""
OUTLIER_SIGMAS = 3.0
"""How many combined expected errors the network's answer may lie from the placement's prediction
before the prediction alone is answered (:func:`with_placement`)."""
SHARED_ERROR_FACTOR = float(np.sqrt(2.0))
"""The weighed answer's expected error over that of the mean of two independent estimates
(:func:`with_placement`): the placement is fitted to the network's answers, so their errors are
not independent (docs/realtime.md gives the calibration measured with it)."""
MOTION_GAIN = 2.0
"""How far a new slice is expected to lie from the placement, over how far the stack stage puts the
latest received slices from it (:func:`placement_error_mm`)."""
LATEST_SLICES = 3
"""How many received slices, the latest by arrival, say where the fetus is now (:func:`placement_error_mm`)."""


def placement_error_mm(expected_mm: NDArray[np.float64], poses: NDArray[np.float64],
                       atlas_from_scanner: NDArray[np.float64], network_from_scanner: NDArray[np.float64],
                       arrival: NDArray[np.int_], usable: NDArray[np.bool_]) -> float | None:
    """How far off the stack's placement ``atlas_from_scanner`` is expected to put a new slice (mm):
    the RMS of the stage's expected errors ``expected_mm`` of the ``usable`` slices (the placement's
    own error) and :data:`MOTION_GAIN` times the RMS E.D. between the stage's ``poses [n, 4, 4]``
    (network frame -> atlas) of the :data:`LATEST_SLICES` latest by ``arrival`` (larger: later)
    and where the placement puts them (the fetus's motion now), in quadrature. None without a
    usable slice.

    Example (two usable slices expected within 2 mm, 1 and 3 mm from the placement):
        >>> poses = np.stack([np.eye(4)] * 3); poses[:, 0, 3] = [9.0, 1.0, 3.0]
        >>> frames = np.stack([np.eye(4)] * 3)
        >>> error = placement_error_mm(np.full(3, 2.0), poses, np.eye(4), frames, np.array([0, 1, 2]),
        ...                            np.array([False, True, True]))
        >>> round(error, 3)                                  # sqrt(2^2 + 2^2 (1^2 + 3^2) / 2)
        4.899
    """
    expected_mm = np.asarray(expected_mm, np.float64)
    usable = np.flatnonzero(np.asarray(usable, bool) & np.isfinite(expected_mm))
    if not len(usable):
        return None
    latest = usable[np.argsort(np.asarray(arrival)[usable], kind="stable")[-LATEST_SLICES:]]
    predicted = atlas_from_scanner @ np.linalg.inv(network_from_scanner[latest])
    motion = anchors.ed(poses[latest], predicted)
    return float(np.sqrt(np.mean(np.square(expected_mm[usable])) + MOTION_GAIN ** 2 * np.mean(np.square(motion))))


def with_placement(pose: NDArray[np.float64], expected_mm: float, predicted: NDArray[np.float64],
                   placement_mm: float) -> tuple[NDArray[np.float64], float]:
    """The network's ``pose`` weighed with the placement's ``predicted`` pose (weights the inverse
    squares of ``expected_mm`` and the placement's expected error ``placement_mm``), expected at
    :data:`SHARED_ERROR_FACTOR` times the two errors' inverse-variance mean; where the two lie more
    than :data:`OUTLIER_SIGMAS` combined errors apart, the prediction alone, expected as far off as
    ``placement_mm`` and never nearer than the network answer it overrules (a sudden move of the
    fetus makes the network right and the placement wrong, and one slice cannot tell which)."""
    if not (np.isfinite(expected_mm) and np.isfinite(placement_mm)):
        return pose, float(expected_mm)                # no figure to weigh by (a degenerate answer)
    if float(anchors.ed(pose, predicted)) > OUTLIER_SIGMAS * float(np.hypot(expected_mm, placement_mm)):
        return predicted.copy(), float(max(placement_mm, expected_mm))
    weights = 1.0 / np.maximum([expected_mm, placement_mm], MIN_WEIGHED_MM) ** 2
    return se3.frechet_mean(np.stack([pose, predicted]), weights), SHARED_ERROR_FACTOR * float(weights.sum() ** -0.5)
