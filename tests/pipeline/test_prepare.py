"""A request's stacks prepared: the stacks without a mask localised one after the other while the
stacks before them are prepared, each answer the one its stack gets alone, in the request's order."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.settings import DEFAULT_MODELS_DIR
from service.inference.model_file import load_model
from service.io.volume import Volume
from service.core.errors import UnusableImage
from service.geometry.pose import index_reversal
from service.pipeline.prepare import localise, localise_uploads, prepare_stack, prepare_stacks
from service.pipeline.stack_upload import StackUpload, check_mask_grid, mask_on_stack_grid


@pytest.fixture(scope="module")
def uploads() -> list[StackUpload]:
    """Two generated whole-uterus stacks without masks around one with its mask (a phantom's), their
    brains where one fetus's would be."""
    from model_export.localiser.scenes import HeadModel, synth_stack
    from tests.support.phantoms import one_fetus_scene, phantom_brain

    image, mask, affine = phantom_brain(11)
    head = HeadModel.from_arrays(image, mask, affine)
    found = one_fetus_scene([synth_stack(head, np.random.default_rng(300 + seed), "heldout") for seed in range(3)])
    volume, truth = found[1]
    return [StackUpload("a.nii.gz", found[0][0]),
            StackUpload("b.nii.gz", volume, Volume(truth.astype(np.uint8), volume.affine), "b_mask.nii.gz"),
            StackUpload("c.nii.gz", found[2][0])]


def test_each_stack_is_prepared_as_it_is_alone_whatever_the_order_of_masks(uploads: list[StackUpload]) -> None:
    info = load_model(DEFAULT_MODELS_DIR / "default" / "model.onnx").info
    prepared = prepare_stacks(uploads, info, True, workers=2)
    assert [p.upload.filename for p in prepared] == ["a.nii.gz", "b.nii.gz", "c.nii.gz"]
    assert [p.localisation.method for p in prepared] == ["network", "mask", "network"]
    for p, u in zip(prepared, uploads):
        alone = prepare_stack(u, info, True)
        assert np.array_equal(p.localisation.mask, alone.localisation.mask)
        assert np.array_equal(p.prepared.inputs, alone.prepared.inputs)
        if u.mask is None:
            assert p.timings["localisation"] > 0


def test_a_young_fetuss_stacks_are_prepared_on_the_localisers_closer_look() -> None:
    """Stacks of a younger pregnancy's scale (the generated stacks' voxels said to be 0.7 times their
    size): /v1/predict's preparation settles each small brain as the localiser does alone, on finer
    pixels where the first look finds it small, not on the model's grid."""
    from model_export.localiser.scenes import HeadModel, synth_stack
    from service.preprocess.localise import SMALL_BRAIN_ML, default_localiser
    from tests.support.phantoms import one_fetus_scene, phantom_brain

    image, mask, affine = phantom_brain(11)
    head = HeadModel.from_arrays(image, mask, affine)
    uploads = []
    for k, (volume, _) in enumerate(one_fetus_scene([synth_stack(head, np.random.default_rng(100 + seed), "heldout")
                                                     for seed in range(2)])):
        smaller = volume.affine.copy()
        smaller[:3, :3] *= 0.7
        uploads.append(StackUpload(f"{k}.nii.gz", Volume(volume.array, smaller)))
    info = load_model(DEFAULT_MODELS_DIR / "default" / "model.onnx").info
    prepared = prepare_stacks(uploads, info, True, workers=2)
    loc = default_localiser()
    for p, u in zip(prepared, uploads):
        alone = loc.localise(u.volume)
        first = loc.settle(u.volume, *loc.probabilities(u.volume))
        assert 0 < first.brain_volume_ml < SMALL_BRAIN_ML
        assert np.array_equal(p.localisation.mask, alone.mask) and not np.array_equal(alone.mask, first.mask)


def test_localise_uploads_gives_every_upload_its_mask_or_the_localisers(uploads: list[StackUpload]) -> None:
    found = localise_uploads(uploads)
    assert [f.method for f in found] == ["network", "mask", "network"]
    for f, u in zip(found, uploads):
        assert np.array_equal(f.mask, localise(u).mask)


@pytest.mark.parametrize("order, reversed_axes", [((1, 0, 2), ()), ((0, 1, 2), (0, 2)), ((2, 0, 1), (1,))])
def test_a_mask_that_stores_its_stacks_voxels_in_another_order_is_taken_in_the_stacks(
        order: tuple[int, int, int], reversed_axes: tuple[int, ...]) -> None:
    """A mask file that holds the stack's voxels with its axes swapped or reversed, its header saying
    so (as a tool that reorients its files writes it), is the stack's mask: brought into the stack's
    order, every voxel where it was in the world. A mask on another grid is left for the check to
    refuse."""
    rng = np.random.default_rng(6)
    affine = np.array([[0.0, 1.1, 0.2, -30.0], [1.1, 0.0, 0.0, 20.0], [0.0, -0.05, 3.0, 5.0], [0, 0, 0, 1.0]])
    stack = Volume(rng.random((12, 10, 5), np.float32), affine)
    mask = rng.random((12, 10, 5)) > 0.5
    stored, file_affine = mask, affine.copy()
    for axis in reversed_axes:
        stored, file_affine = stored[(slice(None),) * axis + (slice(None, None, -1),)], file_affine @ index_reversal(axis, mask.shape[axis])
    permute = np.eye(4)[:, [*order, 3]]                                # the file's voxel -> the reversed array's voxel
    stored, file_affine = stored.transpose(order), file_affine @ permute
    upload = mask_on_stack_grid(StackUpload("s.nii.gz", stack, Volume(stored.astype(np.uint8), file_affine), "m.nii.gz"))
    check_mask_grid(upload)
    np.testing.assert_array_equal(upload.mask.array, mask)
    shifted = Volume(mask.astype(np.uint8), affine @ np.array([[1, 0, 0, 1.0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]))
    with pytest.raises(UnusableImage, match="m.nii.gz is not on the grid"):
        check_mask_grid(mask_on_stack_grid(StackUpload("s.nii.gz", stack, shifted, "m.nii.gz")))


@pytest.mark.parametrize("size, pixel", [(256, 1.17), (512, 0.586)])
def test_a_mask_written_with_a_qform_alone_beside_a_slightly_oblique_sform_is_on_its_grid(
        tmp_path, size: int, pixel: float) -> None:  # noqa: ANN001
    """A stack whose sform is a little off orthogonal (as scanners write them) and its mask saved by
    another tool with the qform alone: the quaternion cannot hold the obliqueness, and the grids'
    corners lie micrometres apart, in proportion to the field of view (a 300 mm grid of 256 or 512
    pixels); the mask is the stack's, stored as it is or with an axis reversed. Moved by a tenth of a
    voxel, it is not."""
    import nibabel as nib

    from service.io.volume import read_volume

    scale = np.diag([pixel / 1.17, pixel / 1.17, 1.0, 1.0])
    affine = np.array([[-1.111, 0.0, 0.9541, 135.7], [-0.0406, -1.1649, -0.3095, 191.1],
                       [0.3705, -0.1275, 2.8273, 52.5], [0.0, 0.0, 0.0, 1.0]]) @ scale
    stack = nib.Nifti1Image(np.random.default_rng(0).random((size, size, 30)).astype(np.float32), None)
    stack.set_sform(affine, code=1)
    stack.set_qform(affine, code=2)
    nib.save(stack, tmp_path / "s.nii.gz")
    for name, shift, flip in (("m.nii.gz", 0.0, False), ("flipped.nii.gz", 0.0, True), ("moved.nii.gz", 0.1, False)):
        moved = affine @ np.array([[1, 0, 0, shift], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
        data = np.zeros((size, size, 30), np.uint8)
        data[: size // 3] = 1
        if flip:
            data, moved = data[::-1], moved @ index_reversal(0, size)
        mask = nib.Nifti1Image(np.ascontiguousarray(data), None)
        mask.set_qform(moved, code=1)
        mask.set_sform(None, code=0)
        nib.save(mask, tmp_path / name)
    volume = read_volume(tmp_path / "s.nii.gz")
    for name in ("m.nii.gz", "flipped.nii.gz"):
        upload = mask_on_stack_grid(StackUpload("s.nii.gz", volume, read_volume(tmp_path / name), name))
        assert 0 < np.abs(upload.mask.affine - volume.affine).max() < 0.01     # not the same numbers, the same grid
        check_mask_grid(upload)
        assert upload.mask.array[: size // 3].all() and not upload.mask.array[size // 3:].any()
    with pytest.raises(UnusableImage, match="moved.nii.gz is not on the grid"):
        check_mask_grid(StackUpload("s.nii.gz", volume, read_volume(tmp_path / "moved.nii.gz"), "moved.nii.gz"))


def test_a_mask_of_fractions_marks_what_its_binary_original_marks() -> None:
    """A probability map with a faint background, and a binary mask resampled with partial volumes,
    mark the brain its binary original marks, not the whole field of view or a blurred rim; whole
    numbers (0 / 255 as floats, a label map) mark every nonzero voxel."""
    from scipy import ndimage

    vol = Volume(np.random.default_rng(5).random((60, 50, 12), np.float32), np.diag([1.2, 1.2, 3.0, 1.0]))
    zz, yy, xx = np.mgrid[:60, :50, :12]
    brain = ((zz - 30) / 18.0) ** 2 + ((yy - 25) / 15.0) ** 2 + ((xx - 6) / 5.0) ** 2 <= 1.0
    binary = localise(StackUpload("s.nii.gz", vol, Volume(brain.astype(np.uint8), vol.affine)))
    blurred = ndimage.gaussian_filter(brain.astype(np.float32), (1.5, 1.5, 0.5))
    for fractions in (0.02 + 0.98 * blurred, blurred):
        found = localise(StackUpload("s.nii.gz", vol, Volume(fractions.astype(np.float32), vol.affine)))
        dice = 2 * (found.mask & binary.mask).sum() / (found.mask.sum() + binary.mask.sum())
        assert dice > 0.95 and abs(found.brain_volume_ml / binary.brain_volume_ml - 1) < 0.06
    labels = brain.astype(np.float32) * 255.0
    labels[brain & (zz < 30)] = 2.0                                 # two labels, both brain
    assert np.array_equal(localise(StackUpload("s.nii.gz", vol, Volume(labels, vol.affine))).mask, binary.mask)


def test_an_uploaded_mask_that_marks_nothing_is_reported_with_no_confidence() -> None:
    """An all-zero mask is the user's word that the stack shows no brain: its slices are empty and its
    localisation says so (confidence 0, 0 ml), not a sure localisation of nothing."""
    vol = Volume(np.random.default_rng(3).random((20, 20, 4), np.float32), np.diag([1.0, 1.0, 3.0, 1.0]))
    found = localise(StackUpload("s.nii.gz", vol, Volume(np.zeros((20, 20, 4), np.uint8), vol.affine)))
    assert found.method == "mask" and found.confidence == 0.0 and found.brain_volume_ml == 0.0 and not found.mask.any()
    box = np.zeros((20, 20, 4), np.uint8)
    box[5:15, 5:15] = 1
    assert localise(StackUpload("s.nii.gz", vol, Volume(box, vol.affine))).confidence == 1.0



def test_the_box_a_mask_marks_is_measured_along_the_scanners_axes_on_an_oblique_grid() -> None:
    """Against every marked voxel's own eight corners placed by the grid: the box around them."""
    from scipy.spatial.transform import Rotation

    from service.pipeline.stack_upload import marked_brain

    affine = np.eye(4)
    affine[:3, :3] = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix() @ np.diag([0.8, 1.1, 3.0])
    affine[:3, 3] = [-40.0, 12.0, 7.5]
    mask = np.zeros((30, 28, 12), np.uint8)
    mask[4:19, 6:25, 3:9] = 1
    mask[20:23, 2:5, 10] = 1                                           # a second, separate part
    mask[10, 10, 11] = 1                                               # a row of the last axis with a gap
    upload = StackUpload("s.nii.gz", Volume(mask.astype(np.float32), affine), Volume(mask, affine), "m.nii.gz")
    volume, extent = marked_brain(upload)
    corners = (np.argwhere(mask)[:, None, :] + (np.array(list(np.ndindex(2, 2, 2))) - 0.5)[None]).reshape(-1, 3)
    world = corners @ affine[:3, :3].T + affine[:3, 3]
    np.testing.assert_allclose(extent, world.max(axis=0) - world.min(axis=0), atol=1e-9)
    assert volume == pytest.approx(mask.sum() * 0.8 * 1.1 * 3.0)


def test_a_region_around_the_other_twin_s_head_finds_that_head_on_every_path() -> None:
    """Twins, the localiser's first choice the first fetus's brain, a box drawn around the second's:
    the brain is the one that reaches into the box, the same one whether the stack is prepared for
    ``/v1/predict`` (alone: no other stack to agree with) or localised for a job; a stream's mask
    frames, each slice's brain as it came, are never taken for a region."""
    from service.inference.model_file import ModelInfo
    from service.preprocess.one_fetus import brain_centre_mm
    from tests.preprocess.test_one_fetus import _ProbabilityLocaliser, _twins

    localiser, volume = _ProbabilityLocaliser(), _twins("first")
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in volume.array.shape], indexing="ij"), -1)
    world = idx @ volume.affine[:3, :3].T + volume.affine[:3, 3]
    box = ((np.abs(world[..., 0] - 60) < 40) & (np.abs(world[..., 1]) < 40)).astype(np.uint8)
    upload = StackUpload("s.nii.gz", volume, Volume(box, volume.affine), "roi.nii.gz")
    assert upload.mask_is_region
    info = ModelInfo(name="m", version="0", backbone="b", label_type="anchor", input_size=32, pixel_spacing_mm=2.0,
                     variance_threshold=1.0, dropout_p=0.1, atlas_id="a", trained_on="-", sha256="0" * 64)
    prepared = prepare_stacks([upload], info, False, localiser=localiser)[0].localisation
    for found in (prepared, localise_uploads([upload], localiser)[0], localise(upload, localiser)):
        assert found.method == "network" and found.brain_volume_ml > 0
        assert brain_centre_mm(found.mask, volume.affine)[0] > 30                # the second twin's, at x = +60 mm
    frames = StackUpload("s", volume, Volume(box, volume.affine), "s (mask frames)", mask_may_be_region=False)
    assert localise(frames, localiser).method == "mask"
