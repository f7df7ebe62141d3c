"""Slices whose brain runs out of the field of view are named in the answer, on the mask given or
found; a stack cropped tight about its brain has none."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from service.inference.estimator import PoseEstimate
from service.io.volume import Volume
from service.pipeline import predict
from service.pipeline.documents import stack_objects
from service.pipeline.prepare import PreparedStack, StackUpload, prepare_stack
from tests.api.conftest import INFO
from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine


def _stack(seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A phantom's stack of 16 axial slices of 1.5 mm pixels and its brain mask."""
    image, mask, affine = phantom_brain(seed)
    shape = (48, 48, 16)
    aff = stack_affine(2, np.eye(3), 1.5, 3.5, shape)
    img, msk = acquire_stack(image, mask, affine, aff, shape, 2, np.broadcast_to(np.eye(4), (16, 4, 4)))
    return img * 3.0 + 20.0, msk > 0, aff


def _answer(img: np.ndarray, msk: np.ndarray, aff: np.ndarray, holds_csf: bool = False,
            ) -> tuple[PreparedStack, list[dict]]:
    upload = StackUpload("s.nii.gz", Volume(img.astype(np.float32), aff), Volume(msk.astype(np.uint8), aff), "m.nii.gz",
                         mask_holds_csf=holds_csf)
    stack = prepare_stack(upload, INFO, bias_correction=False)
    n = len(stack.prepared.inputs)
    part = PoseEstimate(np.repeat(np.eye(4)[None], n, 0), np.ones(n), np.zeros(n, bool), np.zeros(n), np.full(n, 3.0))
    predictions, _ = predict.predict_from_estimates([stack], [part], INFO, INFO.variance_threshold)
    return stack, stack_objects(predictions)[0]["slices"]


def test_the_slices_the_field_of_view_cuts_are_named_and_a_tight_crop_has_none() -> None:
    img, msk, aff = _stack()
    rows = np.flatnonzero(msk.any(axis=(1, 2)))
    cols = np.flatnonzero(msk.any(axis=(0, 2)))
    tight = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    corner = aff @ np.array([tight[0].start, tight[1].start, 0, 1.0])
    tight_aff = aff.copy()
    tight_aff[:3, 3] = corner[:3]
    _, whole = _answer(img, msk, aff)
    _, cropped = _answer(img[tight], msk[tight], tight_aff)
    assert not any(s["cut_by_field_of_view"] for s in whole + cropped)
    yy, xx = np.mgrid[-1:2, -1:2]
    csf = ndimage.binary_dilation(msk, structure=(np.hypot(yy, xx) <= 1.0)[..., None])   # a 1.5 mm CSF rim
    _, rim_cut = _answer(img[tight], csf[tight], tight_aff, holds_csf=True)   # the crop cuts the CSF alone
    assert not any(s["cut_by_field_of_view"] for s in rim_cut)

    depth = int(round(7.0 / 1.5))                                    # the field of view ends 7 mm inside the brain
    ends = slice(0, rows[-1] + 1 - depth)
    stack, sliced = _answer(img[ends], msk[ends], aff)
    named = [s["index"] for s in sliced if s["cut_by_field_of_view"]]
    area = msk.sum(axis=(0, 1))
    middle = np.argsort(area)[-8:]                                  # the slices through the brain's widest part
    assert set(middle.tolist()) <= set(named)
    assert named == np.flatnonzero(stack.cut_by_field_of_view).tolist()


def test_a_mask_that_holds_the_csf_is_judged_beyond_its_csf(monkeypatch) -> None:  # noqa: ANN001
    """The pose network's mask lies its inset inside such a mask: a cut that deep takes the CSF alone."""
    from service.pipeline import prepare
    from service.preprocess.localisation import POSE_MASK_INSET_MM

    img, msk, aff = _stack()
    asked: list[float] = []
    monkeypatch.setattr(prepare, "cut_by_field_of_view",
                        lambda masks, pixel_mm, beyond_mm=0.0: asked.append(beyond_mm) or np.zeros(len(masks), bool))
    for holds in (False, True):
        _answer(img, msk, aff, holds_csf=holds)
    assert asked == [0.0, POSE_MASK_INSET_MM]
