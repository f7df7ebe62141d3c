"""What no stage sees, added to each returned pose's expected error: the request's placement in the
atlas frame, a mirror twin the stage could not rule out, inputs noisier than the network learnt.

The stages' expected errors say how well each slice agrees with its stack's motion model and with
the slices that cross it. A request can agree with itself and still be off as a whole, and a slice
can agree with its stack-mates from its mirror twin; these terms are added last, in quadrature,
for ``/v1/predict``, the stream and the poses a reconstruction job starts from alike.

Example (a slice of expected error 3 mm, a model floor of 1 mm, 2 mm of frame error added):
    >>> from types import SimpleNamespace
    >>> pose = np.array([[0.0, 0, 1, 40], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]])   # far from its twin
    >>> fit = SimpleNamespace(decidable=True, branch_known=True)
    >>> out = SimpleNamespace(expected_error_mm=np.array([3.0]), fit=fit, poses=pose[None], image_consistency=None)
    >>> _ = add_unseen_errors(out, SimpleNamespace(expected_error_floor_mm=1.0), frame_mm=2.0)
    >>> out.expected_error_mm.round(3).tolist()                             # sqrt(9 + 1 + 4)
    [3.742]
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.consistency.stage import StackPoses, misfit_factor
from service.geometry.twin import DEFAULT_PLANE_X_MM, twin_distance_mm, twin_variance, undecided_twin_variance
from service.inference.estimator import PoseEstimate
from service.inference.model_file import ModelInfo
from service.preprocess.noise import noise_error_mm


def add_unseen_errors(out: StackPoses, info: ModelInfo, estimate: PoseEstimate | None = None,
                      input_noise: ArrayLike = np.nan, branch_known: bool | None = None,
                      frame_mm: float = 0.0) -> NDArray[np.float64]:
    """Add to each returned pose's expected error (in place) what no stage sees; return what the
    noise added (mm, in quadrature; shaped as ``input_noise``).

    * Where no image stage weighed the stack's slices again (a stack sent alone, a stream's stack, a
      stack the request could not place), the motion its model did not explain: the stage's
      expected errors times :func:`~service.consistency.stage.misfit_factor`.
    * The request's placement in the atlas frame: the model's ``expected_error_floor_mm``, in quadrature.
    * Inputs noisier than the network learnt (its stack's ``input_noise``, one value or one per
      slice): the model's ``noise_error`` calibration (:func:`~service.preprocess.noise.noise_error_mm`),
      in quadrature. Such a stack is posed worse than its spread says, mostly by a larger turn and
      shift of the whole request, which its slices' agreement cannot show.
    * Where the image stage refined the stack, no less than its placement floor
      (:func:`~service.pipeline.image_stage.placement_floor_mm`): the whole expected error, not a term
      beside the others (the floor is the request's placement, which the first term stands for
      where no stack tells it).
    * In a stack the stage found consistent (each slice's branch set by its stack-mates), the chance
      that a slice sits on its mirror twin all the same: near the mid-sagittal plane a slice and its
      twin show one image, and a sudden move of the fetus can put a slice's stack-mates' prediction
      nearer its twin. The model's ``twin_risk_logit`` gives that chance ``p`` from the slice's
      distance ``d`` to its twin; the expected squared error grows by ``p d^2``
      (:func:`~service.geometry.twin.twin_variance`).
    * Where nothing decided the slice's branch (the stage off, a stack it found inconsistent, a
      consistent stack whose branch neither it nor the request decided, one whose branch the
      request took for it but which fits the request on neither branch, a streamed slice answered
      before its stack's branch is known: ``branch_known`` False; by default the stack fit's
      :attr:`~service.consistency.stack_fit.StackFit.branch_known`), the pose's branch is the
      network's, which a single slice cannot tell: it is on its twin by even odds, and the expected
      squared error grows by half its squared distance to it
      (:func:`~service.geometry.twin.undecided_twin_variance`). A slice near the mid-plane keeps a
      small error and may be accepted; a lateral one does not pass as a sure pose.
    * Last, beside everything else, the request's frame error ``frame_mm`` (what a request the
      network is less sure of than the calibration's acquisitions adds to its placement,
      :func:`~service.consistency.frame_error.frame_error_mm`), in quadrature: a reconstruction job
      and a stream's list of slices worth acquiring again take exactly that off again.

    A slice the network saw without measuring its spread (one MC pass: ``estimate``'s variance NaN)
    has no expected error (NaN, null in the answer): the calibration scales a spread, and the
    floor alone would read as a confident pose.

    Example (a sagittal slice 5 mm off the plane, 10 mm from its twin, in a consistent stack):
        >>> from types import SimpleNamespace
        >>> pose = np.array([[0.0, 0, 1, 5], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]])
        >>> fit = SimpleNamespace(decidable=True, branch_known=True)
        >>> out = SimpleNamespace(expected_error_mm=np.array([3.0]), fit=fit, poses=pose[None], image_consistency=None)
        >>> info = SimpleNamespace(expected_error_floor_mm=4.0, twin_risk_logit=(-1.0, -0.1))
        >>> _ = add_unseen_errors(out, info); out.expected_error_mm.round(2).tolist()   # sqrt(9 + 16 + 11.92)
        [6.08]
    """
    if out.expected_error_mm is None:
        return add_noise_error(out, info, input_noise)
    refined = out.image_consistency
    own = np.asarray(out.expected_error_mm, np.float64) * (misfit_factor(out.fit) if refined is None else 1.0)
    variance = own ** 2 + float(getattr(info, "expected_error_floor_mm", 0.0)) ** 2
    logit = getattr(info, "twin_risk_logit", None)
    known = bool(out.fit is not None and out.fit.branch_known) if branch_known is None else branch_known
    d = twin_distance_mm(out.poses, getattr(info, "symmetry_plane_x_mm", DEFAULT_PLANE_X_MM))
    if not known:
        variance = variance + undecided_twin_variance(d)
    elif logit is not None and out.fit is not None and out.fit.decidable:
        variance = variance + twin_variance(d, logit)
    variance = np.maximum(variance, (refined.placement_floor_mm if refined is not None else 0.0) ** 2)
    variance = variance + float(frame_mm) ** 2              # last, whole: a job and a stream take it off again
    if estimate is not None:
        variance = np.where(estimate.estimated & np.isnan(estimate.variance), np.nan, variance)
    out.expected_error_mm = np.sqrt(variance)
    return add_noise_error(out, info, input_noise)


def add_noise_error(out: StackPoses, info: ModelInfo, input_noise: ArrayLike) -> NDArray[np.float64]:
    """Add to each returned pose's expected error (in place, in quadrature) the model's noise error
    for ``input_noise`` (:func:`~service.preprocess.noise.noise_error_mm`); return what it added.

    Example (a stack of input noise 0.15 under a calibration of onset 0.1 and slope 80 mm: 4 mm):
        >>> from types import SimpleNamespace
        >>> out = SimpleNamespace(expected_error_mm=np.array([3.0, np.nan]))
        >>> added = add_noise_error(out, SimpleNamespace(noise_error=(0.1, 80.0)), 0.15)
        >>> round(float(added), 6), out.expected_error_mm.round(6).tolist()
        (4.0, [5.0, nan])
    """
    added = noise_error_mm(input_noise, getattr(info, "noise_error", None))
    if out.expected_error_mm is not None:
        out.expected_error_mm = np.hypot(out.expected_error_mm, added)
    return added
