"""Slices whose brain lost its signal (a signal void, motion within the slice) are found from their
images, take no part in image consistency, and are named in the answer."""

from __future__ import annotations

import numpy as np
import pytest

from service.inference.estimator import PoseEstimate
from service.io.volume import Volume
from service.pipeline import predict
from service.pipeline.prepare import PreparedStack, StackUpload, prepare_stack
from tests.api.conftest import INFO
from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine

DARK = (6, 7, 8, 9)


def _prepared(dark: tuple[int, ...] = (), gain: float = 0.15, seed: int = 3) -> PreparedStack:
    """A phantom's stack of 16 axial slices with its mask, the brain of slices ``dark`` at ``gain``
    of its signal plus noise (as a signal void leaves it)."""
    image, mask, affine = phantom_brain(seed)
    shape = (48, 48, 16)
    aff = stack_affine(2, np.eye(3), 1.5, 3.5, shape)
    img, msk = acquire_stack(image, mask, affine, aff, shape, 2, np.broadcast_to(np.eye(4), (16, 4, 4)))
    img = img * 3.0 + 20.0
    rng = np.random.default_rng(seed)
    for k in dark:
        inside = msk[..., k] > 0
        img[..., k][inside] = img[..., k][inside] * gain + rng.normal(0, 1.0, inside.sum())
    upload = StackUpload("s.nii.gz", Volume(img.astype(np.float32), aff), Volume(msk.astype(np.uint8), aff), "m.nii.gz")
    return prepare_stack(upload, INFO, bias_correction=False)


def test_the_slices_whose_brain_went_dark_are_found_and_no_others() -> None:
    clean, voided = _prepared(), _prepared(DARK)
    assert not clean.signal_lost.any()
    assert np.flatnonzero(voided.signal_lost).tolist() == list(DARK)
    assert not _prepared(DARK, gain=0.8).signal_lost.any()          # a slice a little darker keeps its signal


def test_slices_without_signal_take_no_part_in_image_consistency(monkeypatch: pytest.MonkeyPatch) -> None:
    stacks = [_prepared(DARK), _prepared()]
    taken: list[list[np.ndarray]] = []                     # each stack's, in the request's order
    monkeypatch.setattr(predict, "refine_where_stacks_cross", lambda prepared, outs, proper, smoothed=None: taken.append(
        [np.array(proper[[p is s for p in prepared].index(True)]) for s in stacks]))
    parts = []
    for s in stacks:
        n = len(s.prepared.inputs)
        degenerate = np.zeros(n, bool)
        degenerate[0] = True
        parts.append(PoseEstimate(np.repeat(np.eye(4)[None], n, 0), np.ones(n), degenerate, np.zeros(n), np.full(n, 3.0)))
    predict.predict_from_estimates(stacks, parts, INFO, INFO.variance_threshold)
    proper = taken[0]
    expected = np.ones(16, bool)
    expected[0] = False                                             # the network's own say: degenerate
    expected[list(DARK)] = False
    assert proper[0].tolist() == expected.tolist()
    assert proper[1].tolist() == ([False] + [True] * 15)


def test_the_answer_names_the_slices_without_signal() -> None:
    from service.streaming.messages import pose_object
    from service.pipeline.documents import stack_objects
    from service.streaming.answers import SliceAnswer

    stack = _prepared(DARK)
    n = len(stack.prepared.inputs)
    part = PoseEstimate(np.repeat(np.eye(4)[None], n, 0), np.ones(n), np.zeros(n, bool), np.zeros(n), np.full(n, 3.0))
    predictions, _ = predict.predict_from_estimates([stack], [part], INFO, INFO.variance_threshold)
    slices = stack_objects(predictions)[0]["slices"]
    assert [s["index"] for s in slices if s["signal_lost"]] == list(DARK)
    ended = [pose_object(SliceAnswer("s", k, predictions[0], k))["signal_lost"] for k in range(n)]   # an ended stack's rows
    assert [k for k, lost in enumerate(ended) if lost] == list(DARK)
    # A stream's slice before its stack ends is a stack of one: nothing to judge it against.
    alone, _ = predict.predict_from_estimates([one_slice(stack, DARK[0])], [part.part(slice(DARK[0], DARK[0] + 1))],
                                              INFO, INFO.variance_threshold, stack_consistency=False)
    assert pose_object(SliceAnswer("s", DARK[0], alone[0], 0))["signal_lost"] is None


def one_slice(stack: PreparedStack, k: int) -> PreparedStack:
    """Slice ``k`` of ``stack`` prepared alone, as a stream prepares a slice before its stack ends."""
    from dataclasses import replace

    from service.preprocess.stack import StackSlices

    sl = stack.slices
    rows = slice(k, k + 1)
    slices = StackSlices(sl.images[rows], sl.masks[rows], sl.pixel_mm, sl.slice_axis, sl.slice_from_voxel[rows], sl.layout)
    prepared = replace(stack.prepared, **{f: getattr(stack.prepared, f)[rows] for f in ("inputs", "mask_fraction", "mask_pixels")})
    return replace(stack, slices=slices, prepared=prepared)
