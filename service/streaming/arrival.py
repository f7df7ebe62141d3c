"""A streamed slice the moment it arrives: its brain, its preparation, its network statistics and its
pose alone (stage 1 of :mod:`service.streaming.session`).

The slice goes through the stages of ``/v1/predict`` as a stack of one slice: its brain (the sent
mask, else the localiser on the slice between its received neighbours, where the brain of the
stack's received slices passes through it:
:meth:`~service.preprocess.localise.Localiser.slice_in_stack`), the service's slice preprocessing,
MC-dropout inference, and the twin-aware statistics of that slice alone. Where the stack's model has
already decided the stack's left-right branch, the slice takes the twin nearer to where that model
puts it, or that place itself where the network's answer is an outlier from it; before, its
expected error allows for either twin (:mod:`~service.streaming.immediate`). N4 needs the whole
stack, so this pose is of the slice as sent.

Example (the received neighbours a localiser sees with slice 4, :data:`WINDOW` a side):
    >>> from types import SimpleNamespace as N
    >>> [f for f in neighbours(N(frames={k: k for k in (2, 3, 4, 6)}), 4)]
    [3, 4]
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from service.consistency.stage import StackPoses
from service.core.errors import InvalidParameter
from service.geometry import anchors, twin
from service.geometry.twin import DEFAULT_PLANE_X_MM
from service.inference.estimator import PoseEstimate, PoseEstimator
from service.io.volume import Volume
from service.pipeline.unseen_errors import add_unseen_errors
from service.pipeline.prepare import PreparedStack, StackUpload
from service.preprocess.localisation import Localisation
from service.preprocess.localise import Localiser
from service.preprocess.noise import input_noise
from service.preprocess.slices import preprocess_slices
from service.preprocess.stack import split_stack
from service.streaming import immediate
from service.streaming.answers import SliceAnswer
from service.streaming.frames import SliceFrame, StreamedStack

WINDOW = 1
"""Neighbours on each side the localiser sees with a slice (when they have arrived)."""


@dataclass
class ReceivedSlice:
    """A received slice: its frame, its preparation alone, its network statistics and what was last sent."""

    frame: SliceFrame
    prepared: PreparedStack
    estimate: PoseEstimate
    network_from_voxel: NDArray[np.float64]          # [1, 4, 4] sent voxel -> this slice's network frame
    answer: SliceAnswer | None = None
    brain_map: NDArray | None = None                 # its localiser map (network grid) while its stack is open


def neighbours(stack: StreamedStack, index: int) -> list[SliceFrame]:
    """The slice ``index`` and its received, contiguous neighbours (up to :data:`WINDOW` a side), by index."""
    lo = hi = index
    while lo - 1 in stack.frames and index - lo < WINDOW:
        lo -= 1
    while hi + 1 in stack.frames and hi - index < WINDOW:
        hi += 1
    return [stack.frames[k] for k in range(lo, hi + 1)]


def prepare_alone(estimator: PoseEstimator, localiser: Localiser | None, frame: SliceFrame, mc_samples: int,
                  masks_hold_csf: bool, around: list[SliceFrame], received: dict[int, NDArray],
                  step_mm: float | None = None) -> ReceivedSlice:
    """``frame`` prepared as a stack of one slice and through the network (``mc_samples`` passes): its
    brain from its mask frame, else from ``localiser`` (:func:`localise_in_window`; ``around``: the
    slice and its :func:`neighbours`)."""
    info = estimator.info
    brain_map = None
    pixels = np.asarray(frame.pixels, dtype=np.float32)[..., None]
    volume = Volume(pixels, np.asarray(frame.scanner_from_voxel, dtype=np.float64), slice_axis=2)
    if frame.mask is not None:
        localisation = Localisation.of(np.asarray(frame.mask, bool)[..., None], volume.spacing, "mask", 1.0,
                                       holds_csf=masks_hold_csf)
    elif localiser is None:
        raise InvalidParameter("slice.mask: no localiser is installed; send a mask frame with every slice")
    else:
        localisation, brain_map = localise_in_window(localiser, frame, around, received, step_mm)
    slices = split_stack(volume, localisation.pose_mask(volume.spacing, axis=2), axis=2)
    prepared = preprocess_slices(slices.images, slices.masks, slices.pixel_mm, info.input_size, info.pixel_spacing_mm)
    stack = PreparedStack(StackUpload(frame.stack, volume), slices, prepared, localisation,
                          input_noise=input_noise(slices.images, slices.masks, slices.pixel_mm, info.pixel_spacing_mm))
    est = estimator.estimate(prepared.inputs, mc_samples)
    return ReceivedSlice(frame, stack, est, stack.network_from_voxel(), brain_map=brain_map)


def localise_in_window(localiser: Localiser, frame: SliceFrame, around: list[SliceFrame], received: dict[int, NDArray],
                       step_mm: float | None = None) -> tuple[Localisation, NDArray]:
    """The brain of ``frame`` by ``localiser``, seen between its received neighbours (``around``, by
    index, the slice among them), where the brain of the stack's slices ``received`` so far passes
    through it (their localiser maps, by index, ``step_mm`` apart;
    :meth:`~service.preprocess.localise.Localiser.slice_in_stack`); and its own map."""
    if len(around) > 1:
        k = [f.index for f in around].index(frame.index)
        affine = np.array(around[0].scanner_from_voxel, dtype=np.float64)
        affine[:3, 2] = (around[-1].scanner_from_voxel[:3, 3] - affine[:3, 3]) / (len(around) - 1)
        window = Volume(np.stack([np.asarray(f.pixels, np.float32) for f in around], axis=-1), affine, slice_axis=2)
    else:
        k, window = 0, Volume(np.asarray(frame.pixels, np.float32)[..., None], frame.scanner_from_voxel, slice_axis=2)
    found, brain_map = localiser.slice_in_stack(window, k, received, frame.index, step_mm)
    region = None if found.pose_region is None else found.pose_region[:, :, k:k + 1]
    return replace(found, mask=found.mask[:, :, k:k + 1], pose_region=region), brain_map


def pose_alone(info: object, state: ReceivedSlice, fit: StackPoses | None, placement_mm: float | None,
               noise: float = float("nan")) -> StackPoses:
    """The slice's own pose and expected error (model ``info``); on the branch of its stack's model
    ``fit`` where that model decided it, weighed with the model's placement (expected ``placement_mm``
    off; :func:`~service.streaming.immediate.with_placement`); the noise error of its stack's input
    ``noise`` so far (over the slices received) added."""
    est = state.estimate
    plane = getattr(info, "symmetry_plane_x_mm", DEFAULT_PLANE_X_MM)
    pose, mass, twinned = est.mean.copy(), est.twin_mass.copy(), np.zeros(1, bool)
    expected = est.spread_mm * getattr(info, "mc_error_scale", 1.0)
    decided = fit is not None and fit.fit is not None and fit.fit.branch_decided and fit.fit.atlas_from_scanner is not None
    if decided:
        predicted = fit.fit.atlas_from_scanner @ state.frame.scanner_from_voxel @ np.linalg.inv(state.network_from_voxel[0])
        other = twin.twin(pose[0], plane)
        if anchors.ed(other, predicted) < anchors.ed(pose[0], predicted):
            pose[0], mass, twinned = other, 1.0 - mass, np.ones(1, bool)
        if placement_mm is not None:
            pose[0], expected[0] = immediate.with_placement(pose[0], float(expected[0]), predicted, placement_mm)
    out = StackPoses(pose, mass, twinned, np.zeros(1, bool), None, expected)
    add_unseen_errors(out, info, est, noise, branch_known=decided)      # a slice alone cannot tell its twin
    return out
