"""A request's slices as the image term samples them: cut to the brain, and side by side."""

from __future__ import annotations

import numpy as np

from service.consistency.slice_images import SampledStack, SampledStacks, StackImages


def test_a_stack_cut_to_its_brain_samples_as_the_whole_slices_do(monkeypatch) -> None:  # noqa: ANN001
    """Cropping to the brain's box plus its margin (blocks of 2 x 2 fine pixels, an odd offset)
    changes no value or gradient the image term samples in and around the brain."""
    import service.consistency.slice_images as module

    rng = np.random.default_rng(3)
    n, h, w = 3, 200, 180
    images = (1.0 + rng.random((n, h, w))).astype(np.float32)
    masks = np.zeros((n, h, w), bool)
    masks[:, 83:121, 61:110] = True
    stack = module.StackImages(images, masks, (0.5, 0.55), np.repeat(np.eye(4)[None], n, 0), np.ones(n, bool))
    cut = module.SampledStack(stack, 3.0)
    monkeypatch.setattr(module, "CROP_MARGIN_MM", 1e6)
    whole = module.SampledStack(stack, 3.0)
    assert cut.images.size < whole.images.size / 3
    inside = np.argwhere(masks[0])[::37]
    mm = np.column_stack([(inside[:, 1] - (w - 1) / 2) * 0.55, (inside[:, 0] - (h - 1) / 2) * 0.5,
                          np.zeros(len(inside)), np.ones(len(inside))])          # slice mm of brain pixels
    which = np.arange(len(inside)) % n
    first = np.zeros(len(which), int)
    cut_all, whole_all = module.SampledStacks([cut]), module.SampledStacks([whole])
    cut_cells = cut_all.cells(first, which, (cut.pixel_from_slice @ mm.T).T)
    whole_cells = whole_all.cells(first, which, (whole.pixel_from_slice @ mm.T).T)
    for name, atol in (("images", 1e-5), ("gradient_rows", 1e-5), ("gradient_cols", 1e-5), ("masks", 1e-6)):
        assert np.allclose(cut_all.sample(getattr(cut_all, name), cut_cells),
                           whole_all.sample(getattr(whole_all, name), whole_cells), atol=atol), name


def test_stacks_side_by_side_sample_as_each_stack_alone() -> None:
    """Points of slices of three stacks of different sizes and pixel spacings, sampled together in
    the flat arrays, read what each stack's own arrays read (images, masks and both gradients;
    points beyond an image read 0)."""
    rng = np.random.default_rng(5)
    stacks = []
    for n, h, w, mm in ((3, 40, 50, 1.0), (5, 64, 48, 0.5), (2, 30, 30, 1.2)):
        masks = np.zeros((n, h, w), bool)
        masks[:, h // 4: 3 * h // 4, w // 4: 3 * w // 4] = True
        images = (1.0 + rng.random((n, h, w))).astype(np.float32)
        stack = StackImages(images, masks, (mm, mm), np.repeat(np.eye(4)[None], n, 0), np.ones(n, bool))
        stacks.append(SampledStack(stack, 2.0))
    together = SampledStacks(stacks)
    stack = rng.integers(0, 3, 400)
    local = np.array([rng.integers(0, len(stacks[s].images)) for s in stack])
    rc = rng.uniform(-2, 70, (400, 2))                                         # some beyond the smaller images
    joint = together.cells(stack, local, rc)
    for s, st in enumerate(stacks):
        mine = stack == s
        alone = SampledStacks([st])
        cells = alone.cells(np.zeros(mine.sum(), int), local[mine], rc[mine])
        for name in ("images", "masks", "gradient_rows", "gradient_cols"):
            assert np.array_equal(SampledStacks.sample(getattr(together, name), joint)[mine],
                                  SampledStacks.sample(getattr(alone, name), cells)), (s, name)
    assert not joint.inside.all() and joint.inside.any()


def test_blocks_brought_back_reproduce_a_ramp_where_they_cover_it() -> None:
    """Averaged over 2 x 3 blocks and brought back linearly, a linear ramp is itself between the
    blocks' centres (a block grid half a block off would shift it by a pixel or more), and flat
    beyond them."""
    from service.consistency.slice_images import _blocks, _unblock

    rows, cols = np.meshgrid(np.arange(20.0), np.arange(31.0), indexing="ij")
    ramp = (2.0 * rows + 0.5 * cols)[None].astype(np.float32)
    back = _unblock(_blocks(ramp, (2, 3)), (2, 3), (20, 31))
    assert back.shape == ramp.shape
    np.testing.assert_allclose(back[0, 1:19, 1:29], ramp[0, 1:19, 1:29], atol=1e-4)
    np.testing.assert_allclose(back[0, :, 29:], back[0, :, 28:29].repeat(2, axis=1), atol=1e-4)   # past the last block


def test_a_wide_gaussian_on_blocks_is_the_gaussian_on_the_pixels() -> None:
    """The coarsest pass's smoothing (4.5 mm on 1.1 and on 0.7 mm pixels) made on 2 x 2 blocks differs
    from the full-resolution Gaussian, and so do its gradients (what the Jacobian samples), by a small
    fraction of the image's (the blur of the blocks and of bringing them back taken off the Gaussian
    on them: 0.2 %, 2.2 % without; blocks of 3 at 0.7 mm left a ripple of 8 % in the gradients), and
    the shading's local mean alike."""
    from scipy import ndimage

    import service.consistency.slice_images as module

    rng = np.random.default_rng(4)
    for pixel in (1.1, 0.7):
        base = ndimage.gaussian_filter(rng.random((3, 120, 130)), (0, 2.2 / pixel, 2.2 / pixel)).astype(np.float32)
        image = (base - base.min()) / np.ptp(base)
        on_blocks = module._wide_gaussian(image, 4.5, (pixel, pixel))
        on_pixels = ndimage.gaussian_filter(image, (0, 4.5 / pixel, 4.5 / pixel))
        inner = (slice(None), slice(15, -15), slice(15, -15))
        assert np.abs(on_blocks - on_pixels)[inner].max() < 0.005 * np.ptp(on_pixels[inner]), pixel
        for got, want in zip(np.gradient(on_blocks, axis=(1, 2)), np.gradient(on_pixels, axis=(1, 2))):
            assert np.sqrt(np.mean((got - want)[inner] ** 2)) < 0.02 * np.std(want[inner]), pixel
    image = image[:, :90, :100]
    masks = np.zeros(image.shape, bool)
    masks[:, 20:70, 25:80] = True
    shaded = (0.5 + image) * np.linspace(0.5, 1.5, 100, dtype=np.float32)
    coarse = module.shading(shaded, masks, (1.1, 1.1))
    blocks, module.BLOCK_SIGMA_PX = module.BLOCK_SIGMA_PX, 100.0       # every Gaussian on the pixels
    try:
        fine = module.shading(shaded, masks, (1.1, 1.1))
    finally:
        module.BLOCK_SIGMA_PX = blocks
    assert np.abs(coarse - fine)[:, 20:70, 25:80].max() < 0.015
    assert np.ptp(fine[:, 20:70, 25:80]) > 0.15                                         # the shading is there


def test_an_image_narrower_than_two_blocks_is_smoothed_on_its_pixels() -> None:
    """A slice three pixels high keeps its shape and is smoothed along its rows on the pixels (no
    block wider than half of it); along its 40 columns, on blocks. An image constant along the
    columns is then exactly the Gaussian along the rows; a slice one pixel high gets a shading too."""
    from scipy import ndimage

    import service.consistency.slice_images as module

    rows = np.random.default_rng(5).random((2, 3, 1)).astype(np.float32)
    image = np.repeat(rows, 40, axis=2)
    out = module._wide_gaussian(image, 4.5, (1.1, 1.1))
    assert out.shape == image.shape
    np.testing.assert_allclose(out, ndimage.gaussian_filter(image, (0, 4.5 / 1.1, 0)), atol=1e-5)
    assert module.shading(image[:, :1], np.ones((2, 1, 40), bool), (1.1, 1.1)).shape == (2, 1, 40)


def test_a_stack_in_very_small_units_is_scaled_as_the_same_stack_in_ordinary_units() -> None:
    """The images are divided by their brain's median however small it is (brain values of 1e-9): the
    image term sees the numbers the same stack stored in ordinary units gives it."""
    from service.consistency.slice_images import BlockedStack

    rng = np.random.default_rng(4)
    images = (50.0 + 100.0 * rng.random((2, 40, 40))).astype(np.float32)
    masks = np.zeros(images.shape, bool)
    masks[:, 10:30, 8:32] = True
    poses = np.repeat(np.eye(4)[None], 2, 0)
    ordinary = BlockedStack.of(StackImages(images, masks, (1.0, 1.0), poses, np.ones(2, bool)))
    small = BlockedStack.of(StackImages(images * np.float32(1e-9), masks, (1.0, 1.0), poses, np.ones(2, bool)))
    np.testing.assert_allclose(small.images, ordinary.images, rtol=1e-5)
