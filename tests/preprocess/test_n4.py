"""N4 in numpy against ITK's filter, and against a bias field that is known."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from service.preprocess.n4 import n4_log_field, sharpen


def _tissue(shape: tuple[int, int, int], seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A head-like phantom: three tissue classes in a blob, a smooth log bias, a little noise."""
    rng = np.random.default_rng(seed)
    axes = np.meshgrid(*(np.linspace(-1, 1, n) for n in shape), indexing="ij")
    r = np.sqrt(sum(a ** 2 for a in axes))
    tissue = np.select([r < 0.4, r < 0.7, r < 0.95], [120.0, 80.0, 150.0], 0.0)
    log_bias = 0.25 * axes[0] - 0.15 * axes[1] ** 2 + 0.1 * axes[0] * axes[2]
    image = tissue * np.exp(log_bias) * (1 + 0.02 * rng.standard_normal(shape))
    return np.maximum(image, 0.0), r < 0.95, log_bias


@pytest.mark.parametrize("shape, seed", [((11, 16, 15), 0), ((24, 20, 9), 1)])
def test_the_field_is_itks_n4_field(shape: tuple[int, int, int], seed: int) -> None:
    image, mask, _ = _tissue(shape, seed)
    itk_image = sitk.GetImageFromArray(image.astype(np.float32))
    n4 = sitk.N4BiasFieldCorrectionImageFilter()
    n4.SetMaximumNumberOfIterations([50, 50])
    n4.Execute(itk_image, sitk.GetImageFromArray(mask.astype(np.uint8)))
    want = sitk.GetArrayFromImage(n4.GetLogBiasFieldAsImage(itk_image))
    got = n4_log_field(image, mask, (50, 50))
    assert np.abs(got - want)[mask].max() < 2e-3
    assert np.ptp(want[mask]) > 0.2                                   # a field worth matching


def test_the_field_follows_a_known_bias_up_to_a_constant() -> None:
    image, mask, log_bias = _tissue((20, 22, 12), 2)
    field = n4_log_field(image, mask)
    residual = (field - log_bias)[mask]
    assert np.std(residual) < 0.25 * np.std(log_bias[mask])


def test_sharpening_narrows_a_blurred_histogram_and_keeps_its_centre() -> None:
    rng = np.random.default_rng(3)
    values = np.concatenate([rng.normal(4.0, 0.08, 4000), rng.normal(4.6, 0.08, 4000)])
    out = sharpen(values)
    for lo, hi in ((3.0, 4.3), (4.3, 5.5)):
        inside = (values > lo) & (values < hi)
        assert out[inside].std() < values[inside].std()
        assert abs(out[inside].mean() - values[inside].mean()) < 0.05


def test_an_empty_or_flat_fit_gives_a_flat_field() -> None:
    assert not n4_log_field(np.ones((6, 6, 4)), np.zeros((6, 6, 4), bool)).any()
    assert not n4_log_field(np.full((1, 1, 1), 5.0), np.ones((1, 1, 1), bool)).any()
    flat = n4_log_field(np.full((8, 8, 5), 50.0), np.ones((8, 8, 5), bool))
    assert np.isfinite(flat).all() and np.ptp(flat) < 1e-6


def test_voxels_that_are_not_finite_or_positive_are_left_out_of_the_fit() -> None:
    image, mask, _ = _tissue((12, 14, 6), 5)
    clean = n4_log_field(image, mask)
    spoilt = image.copy()
    spoilt[6, 7, 3], spoilt[5, 7, 3], spoilt[6, 6, 3] = np.inf, np.nan, -4.0
    field = n4_log_field(spoilt, mask)
    assert np.isfinite(field).all() and np.abs(field - clean).max() < 0.05
