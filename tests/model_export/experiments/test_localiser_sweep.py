"""The localiser sweep's rewrites: other files of the same scan keep every voxel where it was in the world."""

from __future__ import annotations

import numpy as np

from model_export.experiments.localiser_sweep import in_plane_pixels, reordered, reversed_axis, rewrites
from service.geometry.pose import apply
from service.io.volume import Volume
from service.preprocess.stack import slice_axis_of
from tests.support.phantoms import stack_affine

OBLIQUE = np.array([[0.8, -0.6, 0.0], [0.6, 0.8, 0.0], [0.0, 0.0, 1.0]]) @ np.array(
    [[1.0, 0.0, 0.0], [0.0, 0.96, -0.28], [0.0, 0.28, 0.96]])


def _ball_stack(axis: int = 2) -> tuple[Volume, np.ndarray, np.ndarray]:
    """An oblique stack of 1.2 mm pixels and 3 mm slices holding a ball about a known world point:
    the stack, its ball mask and the point."""
    shape = [90, 80, 90]
    shape[axis] = 24
    affine = stack_affine(axis, OBLIQUE, 1.2, 3.0, tuple(shape))
    idx = np.indices(shape).reshape(3, -1).T
    world = apply(affine, idx)
    centre = world.mean(axis=0) + np.array([6.0, -4.0, 3.0])
    inside = (np.linalg.norm(world - centre, axis=1) < 30.0).reshape(shape)
    ramp = (world @ np.array([0.5, 0.3, 0.2])).reshape(shape)            # no two voxels of a line alike
    image = (np.where(inside, 200.0, 40.0) + ramp - ramp.min()).astype(np.float32)
    return Volume(image, affine), inside, centre


def _centroid(volume: Volume, mask: np.ndarray) -> np.ndarray:
    idx = np.argwhere(mask)
    return apply(volume.affine, idx).mean(axis=0)


def test_stored_otherwise_the_stack_and_its_mask_stay_in_place() -> None:
    volume, mask, centre = _ball_stack(axis=1)
    assert np.linalg.norm(_centroid(volume, mask) - centre) < 0.5
    for v, m in [reordered(volume, mask, (1, 0, 2)), reversed_axis(volume, mask, 0), reversed_axis(volume, mask, 2)]:
        np.testing.assert_allclose(_centroid(v, m), _centroid(volume, mask), atol=1e-6)
        # every voxel of the new file holds what the old file held at that world point
        probe = np.array([[3, 5, 7], [20, 10, 4], [v.array.shape[0] - 1, 0, v.array.shape[2] - 2]])
        old = np.rint(apply(np.linalg.inv(volume.affine), apply(v.affine, probe))).astype(int)
        assert ((old >= 0) & (old < volume.array.shape)).all()
        assert [v.array[tuple(p)] for p in probe] == [volume.array[tuple(o)] for o in old]


def test_other_pixel_sizes_keep_the_field_of_view_and_the_ball() -> None:
    volume, mask, centre = _ball_stack(axis=2)
    for pixel_mm in (0.7, 2.0):
        v, m = in_plane_pixels(volume, mask, pixel_mm)
        np.testing.assert_allclose(v.spacing[:2], pixel_mm, rtol=0.03)
        assert v.spacing[2] == volume.spacing[2] and v.array.shape[2] == volume.array.shape[2]
        first, last = v.affine @ [0, 0, 0, 1], v.affine @ [*(np.array(v.array.shape) - 1), 1]
        np.testing.assert_allclose(first, volume.affine @ [0, 0, 0, 1], atol=1e-6)
        np.testing.assert_allclose(last, volume.affine @ [*(np.array(volume.array.shape) - 1), 1], atol=1e-6)
        assert np.linalg.norm(_centroid(v, m) - centre) < 0.6
        assert abs(m.sum() * np.prod(v.spacing) - mask.sum() * np.prod(volume.spacing)) < 0.03 * mask.sum() * np.prod(volume.spacing)


def test_every_rewrite_keeps_the_mask_on_the_stacks_grid_and_the_brain_in_view() -> None:
    volume, mask, centre = _ball_stack(axis=1)
    names = []
    for name, v, m in rewrites(volume, mask, np.random.default_rng(0)):
        names.append(name)
        assert v.array.shape == m.shape and m.any(), name
        assert slice_axis_of(v.spacing) == (0 if name == "slice-axis-first" else 1), name
        if name == "every2nd":                                       # voxel k is the old voxel 2k
            probe = np.array([[5, 7, 3], [30, 2, 11]])
            np.testing.assert_allclose(apply(v.affine, probe), apply(volume.affine, probe * [1, 2, 1]), atol=1e-9)
            assert np.array_equal(v.array[5, 3], volume.array[5, 6]) and np.array_equal(m, mask[:, ::2])
        elif name in ("first-half", "last-half", "edge15"):        # part of the stack, its voxels where they were
            first = np.linalg.solve(volume.affine, v.affine @ [0, 0, 0, 1])[:3]
            np.testing.assert_allclose(first, np.round(first), atol=1e-9)
            assert (0.3 < m.sum() / mask.sum() < 0.7) if name != "edge15" else (0.5 < m.sum() / mask.sum() < 0.95), name
        elif name == "moving":                                       # each slice's content and mask moved alike
            assert abs(int(m.sum()) - int(mask.sum())) <= 0.05 * mask.sum()
            for k in range(v.array.shape[1]):
                if m[:, k].any():
                    shift = _centroid(v, np.where(np.arange(m.shape[1])[None, :, None] == k, m, False)) - \
                        _centroid(volume, np.where(np.arange(mask.shape[1])[None, :, None] == k, mask, False))
                    assert np.linalg.norm(shift) <= np.sqrt(2) * 10.0 + 1.0, (k, shift)
        elif name.startswith("turned"):                              # the content turned about the picture's middle
            middle = apply(volume.affine, (np.array(volume.array.shape) - 1) / 2.0)
            normal = volume.affine[:3, 1] / np.linalg.norm(volume.affine[:3, 1])          # the slice axis: 1
            off = [c - middle - (c - middle) @ normal * normal for c in (_centroid(volume, mask), _centroid(v, m))]
            assert abs(int(m.sum()) - int(mask.sum())) <= 0.05 * mask.sum(), name
            assert abs(np.linalg.norm(off[1]) - np.linalg.norm(off[0])) < 1.0, name      # as far from the middle
            turn = np.degrees(np.arccos(np.clip(off[0] @ off[1] / np.linalg.norm(off[0]) / np.linalg.norm(off[1]), -1, 1)))
            assert abs(turn - float(name.removeprefix("turned"))) < 3.0, (name, turn)
        elif name.startswith("younger"):                             # the same voxels, said to be smaller
            scale = float(name.removeprefix("younger"))
            np.testing.assert_allclose(v.affine[:3, :3], scale * volume.affine[:3, :3], atol=1e-12)
            assert np.array_equal(v.array, volume.array) and np.array_equal(m, mask)
        else:
            assert np.linalg.norm(_centroid(v, m) - centre) < 0.6, name
        if name in ("dark-slice", "signal-void"):                     # one slice of the brain darkened, all or half
            changed = (v.array != volume.array).any(axis=(0, 2))
            assert changed.sum() == 1 and mask[:, changed].any() and np.array_equal(m, mask)
            assert (v.array[:, changed] <= volume.array[:, changed] + 1e-6).all()
        if name == "zero-filled":                                    # one slice of the brain blanked, its mask too
            blank = ~v.array.any(axis=(0, 2))
            assert blank.sum() == 1 and mask[:, blank].any() and not m[:, blank].any()
    assert {"base", "x-reversed", "y-reversed", "in-plane-swapped", "px2.0", "cropped", "cropped-tight", "fov420",
            "noise", "noise15", "moving", "every2nd", "first-half", "last-half", "brain-slab", "zero-filled", "dark-slice", "signal-void",
            "wrap-u", "wrap-v", "edge0",
            "edge15", "turned15", "turned30", "turned45", "younger0.8", "younger0.7"} <= set(names)


def test_a_folded_field_of_view_keeps_the_brain_and_adds_what_lay_beyond() -> None:
    """``wrap-u``: 70 % of the field of view along the first in-plane axis, the brain inside it; what
    lay beyond either end is folded back over the image (the image's energy kept)."""
    from model_export.experiments.localiser_sweep import wrapped

    volume, mask, _ = _ball_stack(axis=2)
    v, m = wrapped(volume, mask, 0, 0.7)
    assert v.array.shape[0] == round(0.7 * volume.array.shape[0]) and m.sum() == mask.sum()
    np.testing.assert_allclose((v.array.astype(np.float64) ** 2).sum(), (volume.array.astype(np.float64) ** 2).sum(),
                               rtol=1e-5)
    start = int(round(np.linalg.solve(volume.affine, v.affine @ [0, 0, 0, 1])[0]))
    assert np.all(v.array >= volume.array[start:start + v.array.shape[0]] - 1e-3)       # folded onto, never less
