"""The network's intensity rescale: the same pictures whatever units a stack is stored in."""

from __future__ import annotations

import numpy as np
import pytest

from service.preprocess.intensity import SAMPLED_VOXELS, rescale_0_255, two_values


@pytest.mark.parametrize("scale", [1e-12, 1e-9, 1e-6, 1e6, 1e20])
def test_the_rescale_does_not_depend_on_the_units_of_the_image(scale: float) -> None:
    rng = np.random.default_rng(0)
    img = rng.normal(100, 10, (3, 30, 30)).astype(np.float32)
    mask = np.zeros(img.shape, bool)
    mask[:, 5:25, 5:25] = True
    mask[2] = False                                            # a slice without brain stays 0
    want = rescale_0_255(img, mask)
    got = rescale_0_255(img * np.float32(scale), mask)
    assert want[:2].max() == pytest.approx(255.0) and not want[2].any()
    np.testing.assert_allclose(got, want, atol=1e-2)


def test_a_flat_slice_rescales_to_zero_whatever_its_level() -> None:
    """One value up to float rounding (a blanked slice, a constant region of interest) holds no picture."""
    rng = np.random.default_rng(1)
    level = np.array([0.0, 1e-9, 100.0, 1e20], np.float32)[:, None, None]
    img = level * (1 + np.float32(1e-7) * rng.standard_normal((4, 8, 8)).astype(np.float32))
    assert not rescale_0_255(img, np.ones(img.shape, bool)).any()


def test_a_mask_is_told_from_an_image_whatever_the_sample_of_its_voxels_sees() -> None:
    """The strided sample only decides that an image is one: a mask whose few brain voxels the sample
    misses is a mask, an image whose few bright voxels it misses an image, one value (blank) neither."""
    size = 4 * SAMPLED_VOXELS
    mask = np.zeros(size, np.uint8)
    mask[1::4][:10] = 255                       # off the sample's stride
    assert two_values(mask) == (0.0, 255.0)
    image = np.zeros(size, np.float32)
    image[1::4][:10] = np.arange(1, 11)
    assert two_values(image) is None and two_values(np.full(size, 7.0)) is None
    assert two_values(np.where(np.arange(size) % 3, -2.5, 40.0)) == (-2.5, 40.0)
