"""A request's frame error: its placement in the atlas frame, from how unsure the network is of its slices.

Every slice of a request shares one error that no stage sees: the whole request turned and shifted in
the atlas frame, its slices in agreement with each other (the common error of
``model_export/experiments/frame_bias.py``). The network's bias on a request's slices grows with
its noise on them: across simulated acquisitions and whole-uterus requests the common error runs at
about a quarter of the network's per-slice error about the stacks' motion models
(:attr:`~service.consistency.stack_fit.StackFit.noise_mm`; docs/reports/accuracy-analyses.md, "The
request's frame error"). The model's expected errors were calibrated on acquisitions whose network
error lies near 12 mm, and their floor holds part of that common error; a request on which the
network is less sure (a stack sent without a mask, whose localiser mask the network did not learn;
a whole-uterus stack of coarse pixels; a real scan) is placed worse. :func:`frame_error_mm` is what
the expected errors lack, ``slope x max(0, sigma - onset)`` (mm, the model's ``frame_error``
calibration, ``model_export/calibrate_frame.py``; its onset may lie under the acquisitions' 12 mm,
which then gain a little too), ``sigma`` the request's network error
(:func:`request_network_error_mm`): the service adds it in quadrature to every slice's expected
error, after every other term (:func:`~service.pipeline.unseen_errors.add_unseen_errors`).

Example (three stacks' network errors of 9, 10 and 24 mm over 20, 20 and 10 slices; onset 13, slope 0.5):
    >>> sigma = request_network_error_mm([9.0, 10.0, 24.0], [20, 20, 10])
    >>> round(sigma, 2), round(float(frame_error_mm(sigma, (13.0, 0.5))), 2)
    (13.7, 0.35)
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core.hinge import hinge_mm


OUTLIER_RATIO = 5.0
"""A stack whose network error is over this many times the request's smallest takes no part in the
request's: the network sees no brain like the others' in it (a mask drawn on another body part, a
stack of another fetus or without a brain). Left in, one such stack's error became every slice's
frame error, and no slice of the request was accepted. The whole-uterus requests and acquisitions
the frame error was calibrated on stay within the ratio (docs/reports/accuracy-analyses.md, "The
request's frame error")."""


def request_network_error_mm(network_error_mm: Sequence[float], slices: Sequence[int]) -> float:
    """A request's network error (mm): the RMS of its stacks' network errors (the stage's fits'
    :attr:`~service.consistency.stack_fit.StackFit.noise_mm`; NaN where a stack had no fit that
    decided) weighted by their ``slices`` (all but the degenerate ones), less the stacks over
    :data:`OUTLIER_RATIO` times the smallest; NaN where no stack has one.

    Example (a stack without a fit counts for nothing, nor one that sees no brain like the others'):
        >>> request_network_error_mm([10.0, float("nan"), 20.0], [30, 5, 10])
        13.228756555322953
        >>> request_network_error_mm([10.0, 12.0, 67.0], [20, 20, 20]) == request_network_error_mm([10.0, 12.0], [20, 20])
        True
        >>> bool(np.isnan(request_network_error_mm([float("nan")], [12])))
        True
    """
    noise = np.asarray(network_error_mm, np.float64)
    finite = noise[np.isfinite(noise)]
    if len(finite):
        noise = np.where(noise > OUTLIER_RATIO * finite.min(), np.nan, noise)
    weight = np.where(np.isfinite(noise), np.asarray(slices, np.float64), 0.0)
    if weight.sum() <= 0:
        return float("nan")
    return float(np.sqrt((weight * np.where(np.isfinite(noise), noise, 0.0) ** 2).sum() / weight.sum()))


def frame_error_mm(sigma_mm: ArrayLike, calibration: tuple[float, float] | None) -> NDArray[np.float64]:
    """The placement error (mm) of a request of network error ``sigma_mm`` beyond what the model's
    expected errors hold: ``slope x max(0, sigma - onset)`` for the model's ``frame_error``
    calibration ``(onset, slope)``; 0 without a calibration or where ``sigma`` is unknown (NaN).

    Example:
        >>> frame_error_mm([10.0, 17.0, float("nan")], (13.0, 0.5)).tolist()
        [0.0, 2.0, 0.0]
        >>> frame_error_mm(30.0, None).tolist()
        0.0
    """
    return hinge_mm(sigma_mm, calibration)
