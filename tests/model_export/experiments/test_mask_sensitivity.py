"""The mask-sensitivity experiment's edited masks: each variant changes the outline as it says."""

from __future__ import annotations

import numpy as np

from model_export.experiments.mask_sensitivity import edit_outline, variants


def _disks(n: int, radius: int = 25, size: int = 80) -> np.ndarray:
    yy, xx = np.mgrid[:size, :size]
    return np.repeat(((yy - size // 2) ** 2 + (xx - size // 2) ** 2 <= radius ** 2)[None], n, axis=0)


def test_bites_remove_and_bulges_add_about_a_disc_at_the_outline() -> None:
    masks = _disks(6)
    disc = np.pi * 8 ** 2
    bitten = edit_outline(masks, 8, False, np.random.default_rng(1))
    bulged = edit_outline(masks, 8, True, np.random.default_rng(1))
    lost = (masks & ~bitten).sum(axis=(1, 2))
    gained = (bulged & ~masks).sum(axis=(1, 2))
    assert not (bitten & ~masks).any() and not (masks & ~bulged).any()
    assert np.all((lost > 0.25 * disc) & (lost < 0.75 * disc))       # about half the disc lies inside
    assert np.all((gained > 0.25 * disc) & (gained < 0.75 * disc))


def test_every_variant_keeps_the_slices_and_dilation_contains_the_truth() -> None:
    masks = _disks(4)
    out = variants(masks, np.random.default_rng(0))
    assert list(out) == ["true", "dilated 2 px", "eroded 2 px", "bite 8 px", "bulge 8 px", "wobble <= 6 px"]
    assert all(v.shape == masks.shape for v in out.values())
    assert np.array_equal(out["true"], masks)
    assert not (masks & ~out["dilated 2 px"]).any() and not (out["eroded 2 px"] & ~masks).any()
    area = masks.sum()
    assert out["dilated 2 px"].sum() > area > out["eroded 2 px"].sum()
    assert (out["wobble <= 6 px"] != masks).any()
