"""The slices a stack file is cut into (:mod:`client.scanner_stack`): against the file's affine, voxel
by voxel, as read from a file, and as the server's stream core puts them back together."""

from __future__ import annotations

import logging
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from client.errors import UnsupportedFile, UnusableInput
from client.scanner_stack import read_stack, scanner_slices


def oblique_affine(spacing: tuple[float, float, float], seed: int, mirrored: bool = False) -> np.ndarray:
    """An oblique affine; ``mirrored``: left-handed (its first column reversed)."""
    affine = np.eye(4)
    affine[:3, :3] = Rotation.from_rotvec(np.random.default_rng(seed).normal(size=3)).as_matrix() * spacing
    if mirrored:
        affine[:3, 0] *= -1.0
    affine[:3, 3] = (-40.0, 12.5, 7.0)
    return affine


@pytest.mark.parametrize("mirrored", [False, True])
@pytest.mark.parametrize(("spacing", "axis"), [((4.0, 1.0, 1.2), 0), ((1.0, 3.5, 1.2), 1), ((1.1, 1.0, 3.0), 2),
                                               ((2.0, 2.0, 2.0), 2), ((3.0, 1.0, 3.0), 2)])
def test_every_pixel_of_every_slice_sits_where_the_file_puts_its_voxel(spacing: tuple[float, float, float],
                                                                       axis: int, mirrored: bool) -> None:
    shape = (7, 6, 5)
    image = np.random.default_rng(1).normal(size=shape).astype(np.float32)
    mask = np.random.default_rng(2).random(shape) > 0.5
    affine = oblique_affine(spacing, seed=axis, mirrored=mirrored)
    got_axis, slices = scanner_slices(image, affine, mask)
    assert got_axis == axis and [s.index for s in slices] == list(range(shape[axis]))
    first, second = [ax for ax in range(3) if ax != axis]
    for s in slices:
        assert s.pixels.shape == (shape[first], shape[second]) and s.mask is not None
        i0, i1 = np.meshgrid(np.arange(shape[first]), np.arange(shape[second]), indexing="ij")
        voxel = np.zeros((*i0.shape, 3), int)
        voxel[..., first], voxel[..., second], voxel[..., axis] = i0, i1, s.index
        in_slice = np.stack([i0, i1, np.zeros_like(i0), np.ones_like(i0)], -1).astype(float)
        in_file = np.concatenate([voxel, np.ones((*i0.shape, 1))], -1).astype(float)
        assert np.allclose(in_slice @ s.scanner_from_voxel.T, in_file @ affine.T, atol=1e-9)
        assert np.array_equal(s.pixels, image[voxel[..., 0], voxel[..., 1], voxel[..., 2]])
        assert np.array_equal(s.mask, mask[voxel[..., 0], voxel[..., 1], voxel[..., 2]])
        assert np.allclose(s.scanner_from_voxel[:3, 2], affine[:3, axis])          # normal x thickness
        assert np.allclose(s.scanner_from_voxel[3], [0, 0, 0, 1])


def test_a_file_is_read_with_its_type_and_its_mask_must_share_its_grid(tmp_path: Path) -> None:
    affine = oblique_affine((1.0, 3.0, 1.0), seed=4)
    image = np.arange(5 * 4 * 3, dtype=np.int16).reshape(5, 4, 3)
    nib.save(nib.Nifti1Image(image, affine), tmp_path / "cor.nii.gz")
    nib.save(nib.Nifti1Image((image % 2).astype(np.uint8), affine), tmp_path / "m.nii.gz")
    nib.save(nib.Nifti1Image(np.zeros((5, 4, 2), np.uint8), affine), tmp_path / "other.nii.gz")
    stack = read_stack(tmp_path / "cor.nii.gz", tmp_path / "m.nii.gz")
    assert (stack.name, stack.slice_axis, len(stack.slices)) == ("cor", 1, 4)
    assert stack.slices[2].pixels.dtype == np.int16 and np.array_equal(stack.slices[2].pixels, image[:, 2, :])
    assert np.array_equal(stack.slices[2].mask, image[:, 2, :] % 2 == 1)
    grid = r"other.nii.gz is not on the grid of its stack cor.nii.gz \(shape \[5, 4, 2\] against \[5, 4, 3\]\)"
    with pytest.raises(UnusableInput, match=grid):
        read_stack(tmp_path / "cor.nii.gz", tmp_path / "other.nii.gz")
    denser = affine @ np.diag([1.0, 1.0, 1.1, 1.0])
    nib.save(nib.Nifti1Image((image % 2).astype(np.uint8), denser), tmp_path / "s.nii.gz")
    with pytest.raises(UnusableInput, match="same shape at another origin, spacing or orientation"):
        read_stack(tmp_path / "cor.nii.gz", tmp_path / "s.nii.gz")
    rgb = np.zeros((5, 4, 3), dtype=[("R", "u1"), ("G", "u1"), ("B", "u1")])
    nib.save(nib.Nifti1Image(rgb, affine), tmp_path / "rgb.nii.gz")
    nib.save(nib.Nifti1Image(image.astype(np.complex64), affine), tmp_path / "complex.nii.gz")
    for name in ("rgb.nii.gz", "complex.nii.gz"):            # refused as the server refuses them, not cast
        with pytest.raises(UnusableInput, match=f"stack: {name}: unsupported pixel type"):
            read_stack(tmp_path / name)
    noise = np.random.default_rng(0).integers(0, 1000, (5, 4, 3, 200)).astype(np.int16).reshape(5, 4, 600)
    nib.save(nib.Nifti1Image(noise, affine), tmp_path / "big.nii.gz")
    data = (tmp_path / "big.nii.gz").read_bytes()
    (tmp_path / "cut.nii.gz").write_bytes(data[: len(data) // 2])      # its voxels cut short: bad input naming it
    for args, what in (((tmp_path / "cut.nii.gz",), "stack"), ((tmp_path / "big.nii.gz", tmp_path / "cut.nii.gz"), "mask")):
        with pytest.raises(UnsupportedFile, match=f"{what}: cut.nii.gz is truncated or corrupt"):
            read_stack(*args)
    for image_class in (nib.Nifti1Image, nib.Nifti2Image):    # a plain NIfTI named .nii.gz: read, as the server reads it
        plain = tmp_path / "plain.nii"
        nib.save(image_class(image, affine), plain)
        named = read_stack(plain)
        plain.rename(tmp_path / "plain.nii.gz")
        misnamed = read_stack(tmp_path / "plain.nii.gz")
        assert np.array_equal(misnamed.slices[2].pixels, image[:, 2, :])
        for a, b in zip(misnamed.slices, named.slices):           # placed where the file says, as read by its name
            np.testing.assert_array_equal(a.scanner_from_voxel, b.scanner_from_voxel)
    gzipped = tmp_path / "gz.nii"                            # and a gzipped one named .nii
    gzipped.write_bytes((tmp_path / "cor.nii.gz").read_bytes())
    assert np.array_equal(read_stack(gzipped).slices[2].pixels, image[:, 2, :])


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_the_server_rebuilds_the_file_from_the_slices_sent(axis: int) -> None:
    """``svrnet stream``'s slices, put back together by the server's stream core: every voxel holds
    the file's value where the file puts it in the scanner, and the slice axis comes from the file's
    rule, which the client copies (``client.scanner_stack`` cannot import the service)."""
    from service.preprocess.stack import slice_axis_of
    from service.streaming.frames import SliceFrame, StreamedStack

    spacing = [1.0, 1.1, 1.2]
    spacing[axis] = 3.0
    shape = (7, 6, 5)
    image = np.random.default_rng(3).normal(size=shape).astype(np.float32)
    affine = oblique_affine(tuple(spacing), seed=axis, mirrored=axis == 1)
    got_axis, slices = scanner_slices(image, affine, None)
    assert got_axis == axis == slice_axis_of(np.linalg.norm(affine[:3, :3], axis=0))
    stack = StreamedStack("s")
    for s in slices[::-1]:
        stack.add(SliceFrame("s", s.index, s.pixels, s.scanner_from_voxel))
    volume, _ = stack.volume()
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in volume.array.shape], indexing="ij"), -1).reshape(-1, 3)
    world = ijk @ volume.affine[:3, :3].T + volume.affine[:3, 3]
    file_ijk = np.rint((world - affine[:3, 3]) @ np.linalg.inv(affine[:3, :3]).T).astype(int)
    assert np.allclose(file_ijk @ affine[:3, :3].T + affine[:3, 3], world, atol=1e-9)
    assert np.array_equal(volume.array[tuple(ijk.T)], image[tuple(file_ijk.T)])


def test_a_file_whose_header_places_its_voxels_nowhere_is_refused_as_the_server_refuses_it(tmp_path: Path) -> None:
    """nibabel places such a file's voxels as the mirror image of where ITK does: the stream's stack
    would sit on the other twin from the same file sent to ``/v1/predict``."""
    img = nib.Nifti1Image(np.ones((8, 8, 4), np.int16), None)              # no affine: both codes 0
    img.header.set_zooms((1.1, 1.1, 3.0))
    nib.save(img, tmp_path / "old.nii.gz")
    with pytest.raises(UnusableInput, match="old.nii.gz: its NIfTI header places its voxels nowhere"):
        read_stack(tmp_path / "old.nii.gz")
    nib.save(nib.Nifti1Image(np.ones((8, 8, 4), np.int16), np.diag([1.1, 1.1, 3.0, 1.0])), tmp_path / "scanner.nii.gz")
    assert len(read_stack(tmp_path / "scanner.nii.gz").slices) == 4


def test_nibabels_notes_on_a_header_it_mends_stay_out_of_the_output(tmp_path: Path,
                                                                      caplog: pytest.LogCaptureFixture) -> None:
    """A file whose ``pixdim`` is zero where its sform places the voxels: nibabel logs that it sets
    them to 1 (printed to the terminal by its own handler); the command's output is the command's."""
    img = nib.Nifti1Image(np.ones((8, 8, 4), np.int16), np.diag([1.1, 1.1, 3.0, 1.0]))
    img.header["pixdim"][1:4] = 0
    nib.save(img, tmp_path / "zero.nii.gz")
    with caplog.at_level(logging.WARNING, logger="nibabel.global"):
        caplog.handler.setLevel(logging.NOTSET)
        stack = read_stack(tmp_path / "zero.nii.gz")
        assert len(stack.slices) == 4 and np.allclose(stack.slices[1].scanner_from_voxel[2, 3], 3.0)
        assert not [r for r in caplog.records if "pixdim" in r.getMessage()]
        nib.load(tmp_path / "zero.nii.gz")                   # what nibabel says where it is not held back
        assert [r for r in caplog.records if "pixdim" in r.getMessage()]


def test_a_mask_that_stores_its_stacks_voxels_in_another_order_is_read_in_the_stacks(tmp_path: Path) -> None:
    """A mask file written by a tool that reorients its files (the stack's voxels, its axes swapped
    and one reversed, the affine saying so) gives each slice the mask the stack's own order gives."""
    affine = oblique_affine((1.0, 3.0, 1.0), seed=5)
    image = np.arange(5 * 4 * 3, dtype=np.int16).reshape(5, 4, 3)
    mask = (image % 3 == 0).astype(np.uint8)
    nib.save(nib.Nifti1Image(image, affine), tmp_path / "cor.nii.gz")
    nib.save(nib.Nifti1Image(mask, affine), tmp_path / "m.nii.gz")
    turned = affine @ np.array([[0, 0, -1, 4], [0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 0, 1.0]])   # new (i,j,k) -> old (4-k, j, i)
    nib.save(nib.Nifti1Image(np.ascontiguousarray(mask[::-1].transpose(2, 1, 0)), turned), tmp_path / "turned.nii.gz")
    plain = read_stack(tmp_path / "cor.nii.gz", tmp_path / "m.nii.gz")
    other = read_stack(tmp_path / "cor.nii.gz", tmp_path / "turned.nii.gz")
    assert all(np.array_equal(a.mask, b.mask) for a, b in zip(plain.slices, other.slices))


@pytest.mark.parametrize("kind", ["signed", "probability"])
def test_a_mask_marks_the_voxels_the_server_takes_from_the_same_file(tmp_path: Path, kind: str) -> None:
    """A mask of 255 saved as signed bytes (-1) and a probability map with a faint background: each
    slice's mask is what the server's rule for an uploaded mask marks (the client counted -1 as
    background and the background's 0.02 as brain)."""
    from service.pipeline.stack_upload import mask_voxels

    affine = oblique_affine((1.0, 1.0, 3.0), seed=2)
    image = np.arange(6 * 5 * 4, dtype=np.int16).reshape(6, 5, 4)
    rng = np.random.default_rng(3)
    brain = rng.random(image.shape) < 0.4
    stored = (np.where(brain, -1, 0).astype(np.int8) if kind == "signed"
              else np.where(brain, rng.uniform(0.6, 1.0, image.shape), 0.02).astype(np.float32))
    nib.save(nib.Nifti1Image(image, affine), tmp_path / "s.nii.gz")
    nib.save(nib.Nifti1Image(stored, affine), tmp_path / "m.nii.gz")
    stack = read_stack(tmp_path / "s.nii.gz", tmp_path / "m.nii.gz")
    server = mask_voxels(stored)
    assert all(np.array_equal(s.mask, server[:, :, k]) and np.array_equal(s.mask, brain[:, :, k])
               for k, s in enumerate(stack.slices))


def test_the_slice_axis_is_the_servers_for_spacings_a_header_rounds_apart() -> None:
    """Near-isotropic voxels whose largest spacings differ by a header's rounding: the client cuts
    its slices along the axis the server's stream core takes."""
    from client.scanner_stack import slice_axis_of
    from service.preprocess.stack import slice_axis_of as server_axis

    for spacing in ([3.0, 1.0, 2.9995], [2.9995, 3.0, 1.0], [1.0, 3.0, 2.99999], [2.0, 2.0, 2.0], [1.0, 4.0, 1.0]):
        assert slice_axis_of(spacing) == server_axis(np.asarray(spacing)), spacing
