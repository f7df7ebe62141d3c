"""A request's stacks prepared: the stacks without a mask localised one after the other while the
stacks before them are prepared, each answer the one its stack gets alone, in the request's order."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.settings import DEFAULT_MODELS_DIR
from service.inference.model_file import load_model
from service.io.volume import Volume
from service.pipeline.prepare import StackUpload, localise, localise_uploads, prepare_stack, prepare_stacks


@pytest.fixture(scope="module")
def uploads() -> list[StackUpload]:
    """Two generated whole-uterus stacks without masks around one with its mask (a phantom's)."""
    from model_export.localiser.scenes import HeadModel, synth_stack
    from tests.support.phantoms import phantom_brain

    image, mask, affine = phantom_brain(11)
    head = HeadModel.from_arrays(image, mask, affine)
    found = [synth_stack(head, np.random.default_rng(300 + seed), "heldout") for seed in range(3)]
    volume, truth = found[1]
    return [StackUpload("a.nii.gz", found[0][0]),
            StackUpload("b.nii.gz", volume, Volume(truth.astype(np.uint8), volume.affine), "b_mask.nii.gz"),
            StackUpload("c.nii.gz", found[2][0])]


def test_each_stack_is_prepared_as_it_is_alone_whatever_the_order_of_masks(uploads: list[StackUpload]) -> None:
    info = load_model(DEFAULT_MODELS_DIR / "default" / "model.onnx").info
    prepared = prepare_stacks(uploads, info, True, workers=2)
    assert [p.upload.filename for p in prepared] == ["a.nii.gz", "b.nii.gz", "c.nii.gz"]
    assert [p.localisation.method for p in prepared] == ["network", "mask", "network"]
    for p, u in zip(prepared, uploads):
        alone = prepare_stack(u, info, True)
        assert np.array_equal(p.localisation.mask, alone.localisation.mask)
        assert np.array_equal(p.prepared.inputs, alone.prepared.inputs)
        if u.mask is None:
            assert p.timings["localisation"] > 0


def test_localise_uploads_gives_every_upload_its_mask_or_the_localisers(uploads: list[StackUpload]) -> None:
    found = localise_uploads(uploads)
    assert [f.method for f in found] == ["network", "mask", "network"]
    for f, u in zip(found, uploads):
        assert np.array_equal(f.mask, localise(u).mask)
