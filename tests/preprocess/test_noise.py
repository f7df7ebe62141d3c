"""The noise a stack carries into the pose network's inputs: rising with the scanner's noise, carried
to the network's pixel size, flagging a low-field stack's."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.settings import DEFAULT_MODELS_DIR
from service.inference.model_file import load_model
from service.io.volume import Volume
from service.pipeline.prepare import StackUpload, prepare_stack
from service.preprocess.noise import NOISY_INPUT, input_noise
from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine

LEVELS = (0.0, 0.03, 0.08, 0.15)
"""Rician noise as a share of the stack's 99th percentile (the acquisition benchmarks' definition)."""


def _noisy_stack(noise: float, pixel_mm: float, seed: int = 0) -> StackUpload:
    """A phantom stack of ``pixel_mm`` pixels and 3 mm slices over a 77 mm field of view with Rician
    noise of ``noise``, and its mask."""
    image, mask, atlas_affine = phantom_brain(3)
    n = int(round(76.8 / pixel_mm))
    shape = (n, n, 18)
    affine = stack_affine(2, np.eye(3), pixel_mm, 3.0, shape)
    img, msk = acquire_stack(image, mask, atlas_affine, affine, shape, 2, np.broadcast_to(np.eye(4), (18, 4, 4)))
    rng = np.random.default_rng(seed)
    sigma = noise * float(np.percentile(img, 99))
    img = np.hypot(img + rng.normal(0, sigma, img.shape), rng.normal(0, sigma, img.shape)).astype(np.float32)
    return StackUpload("s.nii.gz", Volume(img, affine), Volume(msk.astype(np.uint8), affine))


@pytest.fixture(scope="module")
def measured() -> dict[float, list[float]]:
    """Input noise per pixel size, at each of :data:`LEVELS`."""
    info = load_model(DEFAULT_MODELS_DIR / "default" / "model.onnx").info
    return {px: [prepare_stack(_noisy_stack(n, px), info, False).input_noise for n in LEVELS] for px in (0.6, 1.0, 1.6)}


def test_a_low_field_stacks_noise_is_flagged_and_the_benchmarks_is_not(measured: dict[float, list[float]]) -> None:
    for px in (1.0, 1.6):                      # the benchmarks' pixels, and a low-field scanner's coarser ones
        levels = measured[px]
        assert np.all(np.diff(levels) > 0), (px, levels)
        assert levels[0] < 0.005                                  # the phantom's own texture passes little
        assert levels[2] < NOISY_INPUT < levels[3], (px, levels)  # 8 % passes, 15 % does not


def test_the_network_averages_fine_pixels_and_keeps_coarse_ones_noise(measured: dict[float, list[float]]) -> None:
    """The same noise per pixel: (1.25 / 0.6)^2 pixels of 0.6 mm make one input pixel and carry about
    0.6 / 1.25 of the noise; 1.6 mm pixels are interpolated and carry theirs whole (the estimate on
    the resampled inputs read them at 0.4 x a 1 mm stack's)."""
    fine, one, coarse = (measured[px][3] for px in (0.6, 1.0, 1.6))
    assert fine < NOISY_INPUT < one < coarse
    assert abs(fine / one - 0.6 / 1.0) < 0.1


def test_the_estimate_is_the_noise_on_a_smooth_brain_and_ignores_what_lies_outside_it() -> None:
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[:96, :96]
    inside = np.broadcast_to((yy - 48) ** 2 / 30 ** 2 + (xx - 48) ** 2 / 24 ** 2 < 1, (4, 96, 96))
    smooth = 60 + 120 * np.exp(-((yy - 40) ** 2 + (xx - 55) ** 2) / 800.0)
    for sd in (2.0, 8.0, 20.0):
        x = (smooth + rng.normal(0, sd, (4, 96, 96))).astype(np.float32)
        x[~inside] = rng.normal(500, 200, int((~inside).sum()))        # bright, noisy tissue around the brain
        lo, hi = np.percentile(x[inside], [1, 99])
        assert abs(input_noise(x, inside, (1.25, 1.25), 1.25) * (hi - lo) - sd) < 0.1 * sd   # back in image units
    tiny = np.zeros((2, 96, 96), bool)
    tiny[:, 40:45, 40:45] = True                                       # a cap's few pixels: nothing to tell
    assert np.isnan(input_noise(np.ones((2, 96, 96)), tiny, (1.0, 1.0), 1.25))


@pytest.mark.parametrize("factor", [2.0, 1.6])
def test_a_reconstruction_interpolated_to_finer_pixels_reads_its_acquisitions_noise(factor: float) -> None:
    """A 1.1 mm stack with Rician noise of 15 %, written as a scanner's interpolated reconstruction
    (each slice resampled by cubic splines to pixels ``factor`` times finer: 0.55 or 0.69 mm): its
    noise is smooth over the pixels, and the estimate reads it at 0.6-1.5 times the stack written at
    its own pixels, still beyond the calibration (read pixel by pixel, it was 8-17 times lower)."""
    from scipy import ndimage

    upload = _noisy_stack(0.15, 1.1)
    own = input_noise(np.moveaxis(upload.volume.array, 2, 0), np.moveaxis(upload.mask.array > 0, 2, 0), (1.1, 1.1), 1.25)
    n = upload.volume.array.shape[0]
    centres = (np.arange(int(round(n * factor))) + 0.5) / factor - 0.5
    rows, cols = np.meshgrid(centres, centres, indexing="ij")
    fine = np.stack([ndimage.map_coordinates(s, [rows, cols], order=3, mode="nearest")
                     for s in np.moveaxis(upload.volume.array, 2, 0)])
    masks = np.stack([ndimage.map_coordinates(s.astype(np.float32), [rows, cols], order=0) > 0.5
                      for s in np.moveaxis(upload.mask.array, 2, 0)])
    read = input_noise(fine, masks, (1.1 / factor, 1.1 / factor), 1.25)
    assert own > NOISY_INPUT and read > NOISY_INPUT * 0.8
    assert 0.6 < read / own < 1.5, (own, read)
