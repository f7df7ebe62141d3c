"""The noise of a stack's network inputs: measured where the brain is, rising with the scanner's noise."""

from __future__ import annotations

import numpy as np

from service.core.settings import DEFAULT_MODELS_DIR
from service.inference.model_file import load_model
from service.io.volume import Volume
from service.pipeline.prepare import StackUpload, prepare_stack
from service.preprocess.noise import NOISY_INPUT, input_noise
from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine


def _noisy_stack(noise: float, seed: int = 0) -> StackUpload:
    """A phantom stack of 1.2 mm pixels and 3 mm slices with Rician noise of ``noise`` x its 99th
    percentile (the acquisition benchmarks' definition), and its mask."""
    image, mask, atlas_affine = phantom_brain(3)
    shape = (64, 64, 18)
    affine = stack_affine(2, np.eye(3), 1.2, 3.0, shape)
    img, msk = acquire_stack(image, mask, atlas_affine, affine, shape, 2, np.broadcast_to(np.eye(4), (18, 4, 4)))
    rng = np.random.default_rng(seed)
    sigma = noise * float(np.percentile(img, 99))
    img = np.hypot(img + rng.normal(0, sigma, img.shape), rng.normal(0, sigma, img.shape)).astype(np.float32)
    return StackUpload("s.nii.gz", Volume(img, affine), Volume(msk.astype(np.uint8), affine))


def test_the_inputs_noise_rises_with_the_scanners_and_flags_a_low_field_stacks() -> None:
    info = load_model(DEFAULT_MODELS_DIR / "default" / "model.onnx").info
    levels = [prepare_stack(_noisy_stack(n), info, False).input_noise for n in (0.0, 0.03, 0.08, 0.15, 0.25)]
    assert np.all(np.diff(levels) > 0), levels
    assert levels[0] < 0.01                              # the phantom's own texture passes little
    assert levels[1] < NOISY_INPUT < levels[4], levels   # the benchmarks' noise passes, a low-field stack's not


def test_the_estimate_is_the_noise_on_a_smooth_brain_and_ignores_what_lies_outside_it() -> None:
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[:96, :96]
    inside = (yy - 48) ** 2 / 30 ** 2 + (xx - 48) ** 2 / 24 ** 2 < 1
    smooth = 60 + 120 * np.exp(-((yy - 40) ** 2 + (xx - 55) ** 2) / 800.0)
    for sd in (2.0, 8.0, 20.0):
        x = np.where(inside, smooth + rng.normal(0, sd, (4, 96, 96)), 0.0).astype(np.float32)
        assert abs(input_noise(x) - sd / 255) < 0.1 * sd / 255
    tiny = np.zeros((2, 96, 96), np.float32)
    tiny[:, 40:45, 40:45] = 100.0                        # a cap's few pixels: nothing to tell
    assert np.isnan(input_noise(tiny))
