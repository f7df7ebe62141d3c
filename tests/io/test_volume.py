"""World geometry survives SimpleITK (LPS) and nibabel (RAS) writes: LPS/RAS handled once."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from service.geometry import frames, se3
from service.io.volume import Volume, read_volume, to_sitk, write_volume

nib = pytest.importorskip("nibabel", reason="nibabel (dev extra) not installed")


def oblique_affine() -> np.ndarray:
    r = se3.so3_exp(np.array([0.3, -0.5, 0.8]))
    aff = np.eye(4)
    aff[:3, :3] = r * [0.9, 1.1, 3.5]
    aff[:3, 3] = [12.0, -40.0, 7.5]
    return aff


@pytest.mark.parametrize("suffix", [".nii.gz", ".nrrd", ".mha"])
def test_round_trip_through_simpleitk(tmp_path: Path, suffix: str) -> None:
    arr = np.random.default_rng(0).random((5, 6, 7)).astype(np.float32)
    path = tmp_path / f"v{suffix}"
    write_volume(Volume(arr, oblique_affine()), path)
    back = read_volume(path)
    np.testing.assert_allclose(back.affine, oblique_affine(), atol=1e-5)
    np.testing.assert_array_equal(back.array, arr)


def test_simpleitk_written_world_point_matches_nibabel(tmp_path: Path) -> None:
    """A voxel's world position: SimpleITK's LPS point, flipped, equals nibabel's RAS point."""
    arr = np.zeros((5, 6, 7), np.float32)
    path = tmp_path / "v.nii.gz"
    write_volume(Volume(arr, oblique_affine()), path)
    img = sitk.ReadImage(str(path))
    lps = np.array(img.TransformContinuousIndexToPhysicalPoint((1.0, 2.0, 3.0)))
    ras_nib = nib.load(str(path)).affine @ [1, 2, 3, 1]
    np.testing.assert_allclose(np.r_[-lps[0], -lps[1], lps[2]], ras_nib[:3], atol=1e-4)
    np.testing.assert_allclose(read_volume(path).affine @ [1, 2, 3, 1], ras_nib, atol=1e-4)


def test_nibabel_written_file_reads_with_the_same_affine(tmp_path: Path) -> None:
    arr = np.random.default_rng(1).random((4, 5, 6)).astype(np.float32)
    path = tmp_path / "n.nii.gz"
    nib.save(nib.Nifti1Image(arr, oblique_affine()), str(path))
    back = read_volume(path)
    np.testing.assert_allclose(back.affine, oblique_affine(), atol=1e-5)
    np.testing.assert_array_equal(back.array, arr)


def test_world_transform_conjugation() -> None:
    """F T F: an LPS world transform and its RAS rewrite move the same physical point alike."""
    t_lps = se3.exp(np.array([0.2, 0.1, -0.3, 5.0, -2.0, 1.0]))
    t_ras = frames.ras_transform_from_lps(t_lps)
    p_ras = np.array([3.0, 4.0, 5.0, 1.0])
    moved_lps = t_lps @ (frames.LPS_FROM_RAS @ p_ras)
    np.testing.assert_allclose(frames.RAS_FROM_LPS @ moved_lps, t_ras @ p_ras)
    assert np.isclose(np.linalg.det(t_ras[:3, :3]), 1.0)


def test_a_region_keeps_every_voxel_where_it_lies_in_the_world_and_in_simpleitk() -> None:
    """Ground truth: the world point of voxel ``lo + v`` of the whole volume, and ITK's own
    RegionOfInterest of the whole image (an oblique affine, RAS against ITK's LPS)."""
    rng = np.random.default_rng(6)
    vol = Volume(rng.random((30, 26, 9)).astype(np.float32), oblique_affine())
    box = (slice(4, 21), slice(7, 26), slice(2, 6))
    region = vol.region(box)
    lo = np.array([b.start for b in box])
    voxels = np.stack([rng.integers(0, n, 20) for n in region.array.shape], axis=1)
    np.testing.assert_allclose((region.affine @ np.c_[voxels, np.ones(20)].T)[:3],
                               (vol.affine @ np.c_[voxels + lo, np.ones(20)].T)[:3], atol=1e-9)
    np.testing.assert_array_equal(region.array, vol.array[box])
    ours = to_sitk(region)
    itk = sitk.RegionOfInterest(to_sitk(vol), [int(b.stop - b.start) for b in box], [int(b.start) for b in box])
    np.testing.assert_allclose(ours.GetOrigin(), itk.GetOrigin(), atol=1e-9)
    np.testing.assert_allclose(ours.GetDirection(), itk.GetDirection(), atol=1e-12)
    np.testing.assert_allclose(ours.GetSpacing(), itk.GetSpacing(), atol=1e-12)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(ours), sitk.GetArrayFromImage(itk))


def test_a_grid_near_right_angles_is_written_where_its_affine_puts_its_voxels() -> None:
    """A grid 0.03 deg off right angles (within what a file may hold) goes through ITK with the nearest
    rotation as its direction: written and read back, every corner voxel lies within the shear's
    reach (0.0005 x its distance from the origin) of where the original affine puts it."""
    import tempfile

    affine = np.diag([-0.8, 0.8, 3.0, 1.0])
    affine[:3, 3] = (40.0, -60.0, 12.0)
    affine[0, 1] = 0.8 * 5e-4                                   # the second axis leans 0.03 deg towards the first
    shape = (100, 90, 20)
    with tempfile.TemporaryDirectory() as d:
        write_volume(Volume(np.zeros(shape, np.float32), affine), Path(d) / "g.nii.gz")
        back = read_volume(Path(d) / "g.nii.gz")
    corners = np.array([[i, j, k, 1.0] for i in (0, shape[0] - 1) for j in (0, shape[1] - 1) for k in (0, shape[2] - 1)])
    truth, written = corners @ affine.T, corners @ back.affine.T
    reach = 5e-4 * np.linalg.norm(truth[:, :3] - affine[:3, 3], axis=1) + 1e-4
    assert (np.linalg.norm(written[:, :3] - truth[:, :3], axis=1) <= reach).all()
    assert np.linalg.norm(written[0, :3] - truth[0, :3]) < 1e-4            # the first voxel where it was
