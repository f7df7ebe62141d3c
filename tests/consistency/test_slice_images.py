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
