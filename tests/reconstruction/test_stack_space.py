"""Each stack's frame against a simulated truth: a phantom brain acquired by a stack whose scanner
frame is turned and shifted from the atlas, with and without motion between its slices; the volume
placed there (written to NIfTI and read back) overlays the stack it was placed by."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.geometry import se3, sampling
from service.geometry.pose import apply, make_pose
from service.io.volume import Volume, read_volume, write_volume
from service.reconstruction.export import volume_in_stack_space
from service.reconstruction.stack_space import NoStackFrame, StackFrame, in_stack_space, stack_frame, stack_frames
from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine

SHAPE = (48, 48, 16)
SCANNER_FROM_ATLAS = make_pose(se3.so3_exp([0.2, -0.35, 0.5]), [15.0, -40.0, 62.0])   # the head in the scanner


def acquisition(motion_sd: tuple[float, float], seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A stack of the phantom along z: its file affine (voxel -> scanner), each slice's true
    ``atlas_from_voxel``, and the slices' motion (atlas_from_atlas) about the head's place."""
    rng = np.random.default_rng(seed)
    atlas_geometry = stack_affine(2, se3.so3_exp([0.1, 0.0, -0.2]), 1.5, 3.5, SHAPE)
    affine = SCANNER_FROM_ATLAS @ atlas_geometry
    g = se3.exp(np.concatenate([rng.normal(scale=motion_sd[0], size=(SHAPE[2], 3)),
                                rng.normal(scale=motion_sd[1], size=(SHAPE[2], 3))], axis=1))
    motion = g @ se3.inverse(SCANNER_FROM_ATLAS)[None]               # atlas_from_scanner per slice
    return affine, motion @ affine, motion


def test_a_still_head_s_frame_is_the_scanner_frame_it_was_acquired_in() -> None:
    affine, atlas_from_voxel, _ = acquisition((0.0, 0.0))
    frame = stack_frames(atlas_from_voxel, np.broadcast_to(affine, atlas_from_voxel.shape), np.zeros(SHAPE[2], int),
                         np.ones(SHAPE[2]))[0]
    np.testing.assert_allclose(frame.scanner_from_atlas, SCANNER_FROM_ATLAS, atol=1e-9)
    assert frame.slices == SHAPE[2] and frame.motion_mm < 1e-6


def test_a_moving_head_s_frame_is_its_mean_place_and_its_motion_is_reported() -> None:
    affine, atlas_from_voxel, motion = acquisition((0.03, 1.5))
    frame = stack_frames(atlas_from_voxel, np.broadcast_to(affine, atlas_from_voxel.shape), np.zeros(SHAPE[2], int),
                         np.ones(SHAPE[2]))[0]
    seen = apply(se3.inverse(motion), np.array([0.0, 2.0, 8.0]))     # where each slice saw the brain's centre
    assert np.linalg.norm(apply(frame.scanner_from_atlas, [0.0, 2.0, 8.0]) - seen.mean(axis=0)) < 0.3
    turns = np.linalg.norm(se3.so3_log(np.swapaxes(frame.scanner_from_atlas[:3, :3], 0, 1) @ se3.inverse(motion)[:, :3, :3]),
                           axis=1)
    assert np.degrees(np.median(turns)) < 3.0                         # amid the slices' turns of 1.7 degrees
    assert 1.0 < frame.motion_mm < 6.0                                # 1.5 mm and 1.7 degrees a slice


def test_slices_out_of_the_volume_take_no_part_and_a_stack_without_any_has_no_frame() -> None:
    affine, atlas_from_voxel, _ = acquisition((0.0, 0.0))
    wild = atlas_from_voxel.copy()
    wild[:4] = make_pose(se3.so3_exp([1.0, 0.0, 0.0]), [50.0, 0.0, 0.0]) @ wild[:4]   # off, and out of the volume
    weights = np.r_[np.zeros(4), np.ones(SHAPE[2] - 4)]
    stacks = np.r_[np.zeros(SHAPE[2], int), np.ones(3, int)]
    poses = np.concatenate([wild, atlas_from_voxel[:3]])
    frames = stack_frames(poses, np.broadcast_to(affine, poses.shape), stacks, np.r_[weights, np.zeros(3)])
    np.testing.assert_allclose(frames[0].scanner_from_atlas, SCANNER_FROM_ATLAS, atol=1e-9)
    assert frames[0].slices == SHAPE[2] - 4
    assert frames[1] == StackFrame(1, None, 0, None)
    assert frames[1].as_json() == {"stack": 1, "slices": 0, "scanner_from_atlas": None, "motion_mm": None,
                                  "nifti_codes": None, "qform_from_sform": None, "nifti_spatial_unit": None}
    with pytest.raises(NoStackFrame, match="stack 1 has no slice"):
        in_stack_space(np.eye(4), frames[1])


def test_a_mirrored_slice_map_takes_no_part() -> None:
    """A pose of the other handedness than its stack's file has no rotation near it: it is left out,
    not projected onto an arbitrary one."""
    affine, atlas_from_voxel, _ = acquisition((0.0, 0.0))
    mirrored = atlas_from_voxel.copy()
    mirrored[:3] = np.diag([-1.0, 1.0, 1.0, 1.0]) @ mirrored[:3]
    frame = stack_frames(mirrored, np.broadcast_to(affine, mirrored.shape), np.zeros(SHAPE[2], int), np.ones(SHAPE[2]))[0]
    assert frame.slices == SHAPE[2] - 3
    np.testing.assert_allclose(frame.scanner_from_atlas, SCANNER_FROM_ATLAS, atol=1e-9)


def test_a_report_s_frame_is_found_or_the_reason_it_is_not_is_given(tmp_path: Path) -> None:
    entry = {"stack": 0, "slices": 5, "scanner_from_atlas": SCANNER_FROM_ATLAS.tolist(), "motion_mm": 0.4}
    report = {"stack_frames": [entry, {"stack": 1, "slices": 0, "scanner_from_atlas": None, "motion_mm": None}]}
    np.testing.assert_allclose(stack_frame(report, 0).scanner_from_atlas, SCANNER_FROM_ATLAS)
    for bad, words in (({}, "earlier version"), (report, "stacks are 0-1"), (report, "no slice")):
        with pytest.raises(NoStackFrame, match=words):
            stack_frame(bad, 2 if words == "stacks are 0-1" else 1)
    with pytest.raises(OSError):
        volume_in_stack_space(tmp_path / "gone.nii.gz", report, 0, tmp_path / "placed.nii.gz")


def test_the_atlas_volume_placed_by_the_frame_overlays_the_stack_through_a_nifti_file(tmp_path: Path) -> None:
    """The composition end to end, as the API serves it: the phantom in atlas space written as the
    job's volume, placed with the stack's frame from its report entry, written and read as NIfTI, sampled at the stack's voxel centres (scanner mm from the stack's file) gives
    the stack's intensities; left in atlas space it does not."""
    image, mask, brain_affine = phantom_brain(2)
    affine, atlas_from_voxel, motion = acquisition((0.0, 0.0))
    stack, inside = acquire_stack(image, mask, brain_affine, affine, SHAPE, 2, motion)
    frame = stack_frames(atlas_from_voxel, np.broadcast_to(affine, atlas_from_voxel.shape), np.zeros(SHAPE[2], int),
                         np.ones(SHAPE[2]))[0]
    write_volume(Volume(image, brain_affine), tmp_path / "volume.nii.gz")          # the job's atlas-space volume
    report = {"stack_frames": [frame.as_json()]}
    placed = read_volume(volume_in_stack_space(tmp_path / "volume.nii.gz", report, 0, tmp_path / "placed.nii.gz"))
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in SHAPE], indexing="ij"), -1).astype(np.float64)
    scanner = apply(affine, ijk)

    def ncc(volume_affine: np.ndarray) -> float:
        seen = sampling.sample_points(placed.array, volume_affine, scanner)[inside]
        return float(np.corrcoef(seen, stack[inside])[0, 1]) if seen.std() > 0 else 0.0

    assert ncc(placed.affine) > 0.99
    assert ncc(brain_affine) < 0.5                                   # the atlas-space volume misses it


@pytest.mark.parametrize("codes", [(1, 2), (2, 1), (1, 1)])
def test_a_stack_whose_qform_and_sform_differ_gets_a_volume_every_reader_places_as_it_places_the_stack(
        codes: tuple[int, int], tmp_path: Path) -> None:
    """A stack file whose qform lies 15 mm and 8 degrees from its sform is placed by the sform in the
    service and nibabel, and by the qform in ITK (its sform code other than 1): the volume placed in
    its coordinates carries the stack's codes and a qform moved as the stack's is, so that in either
    reader each volume voxel lies on the stack voxel the service says it does."""
    sitk = pytest.importorskip("SimpleITK")
    nib = pytest.importorskip("nibabel")
    from service.io.readers import read_upload
    from service.reconstruction.stack_space import with_header

    affine, atlas_from_voxel, _ = acquisition((0.0, 0.0))
    move = make_pose(se3.so3_exp([0.0, 0.14, 0.0]), [15.0, 0.0, 4.0])        # qform = move @ sform
    stack_file = nib.Nifti1Image(np.random.default_rng(1).random(SHAPE).astype(np.float32), affine)
    stack_file.set_sform(affine, codes[1])
    stack_file.set_qform(move @ affine, codes[0])
    nib.save(stack_file, tmp_path / "stack.nii.gz")
    upload = read_upload(tmp_path / "stack.nii.gz", "stack.nii.gz")
    np.testing.assert_allclose(upload.affine, affine, atol=1e-4)               # the service reads the sform
    frame = stack_frames(atlas_from_voxel, np.broadcast_to(affine, atlas_from_voxel.shape), np.zeros(SHAPE[2], int),
                         np.ones(SHAPE[2]))[0]
    entry = with_header(frame, upload.nifti).as_json()
    assert entry["nifti_codes"] == list(codes)
    np.testing.assert_allclose(entry["qform_from_sform"], move, atol=1e-4)
    image, _, brain_affine = phantom_brain(2)
    write_volume(Volume(image, brain_affine), tmp_path / "volume.nii.gz")
    placed = volume_in_stack_space(tmp_path / "volume.nii.gz", {"stack_frames": [entry]}, 0, tmp_path / "placed.nii.gz")
    voxels = np.array([[0.0, 0.0, 0.0], [30.0, 12.0, 40.0], [55.0, 63.0, 2.0]])
    on_stack = apply(np.linalg.inv(affine) @ frame.scanner_from_atlas @ brain_affine, voxels)   # the service's word
    for read in ("nibabel", "itk"):
        if read == "nibabel":
            volume_world = apply(nib.load(placed).affine, voxels)
            stack_world = apply(nib.load(tmp_path / "stack.nii.gz").affine, on_stack)
        else:
            vol, stk = sitk.ReadImage(str(placed)), sitk.ReadImage(str(tmp_path / "stack.nii.gz"))
            volume_world = np.array([vol.TransformContinuousIndexToPhysicalPoint(tuple(v)) for v in voxels])
            stack_world = np.array([stk.TransformContinuousIndexToPhysicalPoint(tuple(v)) for v in on_stack])
        np.testing.assert_allclose(volume_world, stack_world, atol=1e-3, err_msg=read)


@pytest.mark.parametrize("units", [1, 3])
def test_a_stack_in_metres_or_microns_gets_a_volume_itk_places_on_it(units: int, tmp_path: Path) -> None:
    """ITK scales a qform by the distance unit the header names (nibabel and the service read mm): the
    volume placed in such a stack's coordinates names the stack's unit, so that in ITK each volume
    voxel lies on the stack voxel the service says it does, as in nibabel."""
    sitk = pytest.importorskip("SimpleITK")
    nib = pytest.importorskip("nibabel")
    from service.io.readers import read_upload
    from service.reconstruction.stack_space import with_header

    affine, atlas_from_voxel, _ = acquisition((0.0, 0.0))
    stack_file = nib.Nifti1Image(np.zeros(SHAPE, np.float32), affine)
    stack_file.set_sform(affine, 1)
    stack_file.set_qform(affine, 1)
    stack_file.header["xyzt_units"] = units
    nib.save(stack_file, tmp_path / "stack.nii.gz")
    upload = read_upload(tmp_path / "stack.nii.gz", "stack.nii.gz")
    frame = stack_frames(atlas_from_voxel, np.broadcast_to(affine, atlas_from_voxel.shape), np.zeros(SHAPE[2], int),
                         np.ones(SHAPE[2]))[0]
    image, _, brain_affine = phantom_brain(2)
    write_volume(Volume(image, brain_affine), tmp_path / "volume.nii.gz")
    entry = with_header(frame, upload.nifti).as_json()
    placed = volume_in_stack_space(tmp_path / "volume.nii.gz", {"stack_frames": [entry]}, 0, tmp_path / "placed.nii.gz")
    voxels = np.array([[0.0, 0.0, 0.0], [30.0, 12.0, 40.0]])
    on_stack = apply(np.linalg.inv(affine) @ frame.scanner_from_atlas @ brain_affine, voxels)
    vol, stk = sitk.ReadImage(str(placed)), sitk.ReadImage(str(tmp_path / "stack.nii.gz"))
    np.testing.assert_allclose([vol.TransformContinuousIndexToPhysicalPoint(tuple(v)) for v in voxels],
                               [stk.TransformContinuousIndexToPhysicalPoint(tuple(v)) for v in on_stack],
                               rtol=1e-5, atol=1e-3)
