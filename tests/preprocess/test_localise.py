"""Brain localisation: the geometry step, the confidence, and the shipped localiser on generated
whole-uterus phantoms, on noise, and on the real scans of ../shared/data (skipped without them)."""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
import pytest
from scipy import ndimage

from service.core.settings import DEFAULT_LOCALISERS_DIR
from service.io.volume import Volume, read_volume
from service.preprocess.localise import Localiser, Localisers
from tests.conftest import SHARED_DATA

REAL = SHARED_DATA / "real_scans"


def dice(a: np.ndarray, b: np.ndarray) -> float:
    return float(2 * (a & b).sum() / max(a.sum() + b.sum(), 1))


@pytest.fixture(scope="module")
def localiser() -> Localiser:
    return Localiser.load(DEFAULT_LOCALISERS_DIR / "default" / "model.onnx")


@pytest.fixture(scope="module")
def generated() -> Callable[[int], tuple[Volume, np.ndarray]]:
    """``generated(seed)``: the whole-uterus stack of the phantom brain of seed 11 drawn with scene
    seed ``seed`` (held-out style) and its brain mask, made once a module for the tests that read it
    (2-3 s a stack; several tests draw the same seeds). Its voxels and mask are read-only: a test
    that wrote into them would fail rather than change another test's stack."""
    from model_export.localiser.scenes import HeadModel, synth_stack
    from tests.support.phantoms import phantom_brain

    head = HeadModel.from_arrays(*phantom_brain(11))

    @functools.cache
    def draw(seed: int) -> tuple[Volume, np.ndarray]:
        volume, truth = synth_stack(head, np.random.default_rng(seed), "heldout")
        volume.array.flags.writeable = False
        truth.flags.writeable = False
        return volume, truth

    return draw


@pytest.fixture(scope="module")
def heldout_stack(generated: Callable[[int], tuple[Volume, np.ndarray]]) -> Volume:
    """The generated stack of scene seed 7."""
    return generated(7)[0]


def test_the_registry_names_what_it_lacks() -> None:
    from service.core.errors import NotFound

    with pytest.raises(NotFound, match="model: unknown localiser 'other'"):
        Localisers.from_directory(DEFAULT_LOCALISERS_DIR).get("other")


def test_the_shipped_localiser_finds_the_brain_of_a_generated_whole_uterus_stack(localiser: Localiser,
                                                                                 generated: Callable) -> None:
    scores = []
    for seed in range(3):
        volume, truth = generated(100 + seed)
        found = localiser.localise(volume)
        assert found.mask.shape == volume.array.shape and found.method == "network"
        scores.append(dice(found.mask, truth))
    assert np.median(scores) > 0.8, scores


def test_batches_run_side_by_side_give_the_logits_of_one_call(localiser: Localiser, heldout_stack: Volume) -> None:
    """Two network calls at a time, each on half the cores, are a matter of speed: every batch's
    logits, the mirrored pass's too, land where one call on the whole stack puts them."""
    from service.core.threads import available_cores
    from service.preprocess.localiser_inputs import localiser_inputs

    volume = heldout_stack
    x, _ = localiser_inputs(volume, localiser.grid_mm)
    name = localiser.session.get_inputs()[0].name
    whole = lambda inputs: localiser.session.run(None, {name: np.ascontiguousarray(inputs)})[0][:, 0]  # noqa: E731
    expected = 0.5 * (whole(x) + whole(x[..., ::-1])[..., ::-1])
    assert len(x) > 2 * 8 and localiser.side_by_side == (available_cores() >= 2)
    for threads in (0, 1):
        loaded = Localiser.load(localiser.path, threads=threads)
        assert loaded.side_by_side == (threads == 0 and available_cores() >= 2)
        assert np.abs(loaded._logits(name, x) - expected).max() < 1e-4


def test_a_zero_filled_slice_through_the_brain_does_not_cut_it_in_two(localiser: Localiser, generated: Callable) -> None:
    """A slice a scanner or converter filled with zeros, in the middle of the brain, holds no image:
    it gets no mask, and the brain on either side of it is found as in the stack without it (the
    network sees nothing there; the geometry took the gap for the brain's end and kept one half)."""
    from service.preprocess.stack import stack_axis

    volume, truth = generated(101)
    axis = stack_axis(volume)
    found = np.moveaxis(localiser.localise(volume).mask, axis, 0)
    brain = np.flatnonzero(np.moveaxis(truth, axis, 0).reshape(truth.shape[axis], -1).any(1))
    middle = int(brain[len(brain) // 2])
    array = np.moveaxis(volume.array.copy(), axis, 0)
    array[middle] = 0.0
    blanked = np.moveaxis(localiser.localise(Volume(np.moveaxis(array, 0, axis), volume.affine)).mask, axis, 0)
    assert not blanked[middle].any()
    others = np.arange(len(array)) != middle
    assert dice(blanked[others], found[others]) > 0.95
    assert blanked[:middle].any() and blanked[middle + 1:].any()


def test_a_stack_whose_file_stores_its_in_plane_voxels_in_any_order_gets_the_same_mask(localiser: Localiser,
                                                                                       heldout_stack: Volume) -> None:
    """The localiser sees each slice laid out by the scanner's axes: a file that stores the stack's
    rows or columns reversed or its two in-plane axes swapped (its header saying so) gives the network
    the same pictures, so the same probabilities and the same mask voxel for voxel, with the
    mirrored pass and without it (where the file's own order was seen, the same stack stored
    transposed lost its accepted slices: docs/reports/localiser-experiments.md). The probabilities
    compared are those ``localise`` itself computed on the model's grid (its first
    ``probabilities_of`` call): one network run a storage, not two."""
    from model_export.experiments.localiser_sweep import STORAGES, stored_as

    volume = heldout_stack
    for mirrored in (localiser.mirrored, False):          # as loaded, and without the mirrored pass
        loc = Localiser(**{**localiser.__dict__, "mirrored": mirrored})     # a copy: the spy stays on it
        runs = []
        network = loc.probabilities_of
        loc.probabilities_of = lambda volumes, grids_mm=None: runs.append(network(volumes, grids_mm)) or runs[-1]

        def localised(v: Volume):  # noqa: ANN202 - the Localisation and the model-grid probabilities it rests on
            runs.clear()
            found = loc.localise(v)
            assert runs and len(runs[0]) == 1 and runs[0][0][1].grid_mm == loc.grid_mm
            return found, runs[0][0][0]

        found, prob = localised(volume)
        assert np.array_equal(prob, Localiser.probabilities(loc, volume)[0])     # what probabilities() says
        assert found.mask.sum() > 1000
        for storage in STORAGES[1:]:
            other = stored_as(volume, *storage)
            there, prob_other = localised(other)
            assert np.array_equal(prob_other, prob), storage
            assert np.array_equal(there.mask, stored_as(Volume(found.mask, volume.affine), *storage).array), storage
            assert there.brain_volume_ml == found.brain_volume_ml and there.confidence == found.confidence


def test_a_stack_whose_file_stores_its_slices_last_to_first_gets_the_same_mask(localiser: Localiser,
                                                                              heldout_stack: Volume) -> None:
    """The network sees each slice between its neighbours and the geometry walks the slices: both
    see a stack's slices in one order whichever way its file stores them, so the mask is the same
    voxel for voxel (one of the two files is seen last to first); without that order the two files
    got masks that differed in their end slices (real stacks by 1,300-3,300 voxels)."""
    from service.geometry.pose import index_reversal
    from service.preprocess.localise import reversed_slices
    from service.preprocess.stack import stack_axis

    volume = heldout_stack
    axis = stack_axis(volume)
    stored = Volume(np.ascontiguousarray(np.flip(volume.array, axis)),
                    volume.affine @ index_reversal(axis, volume.array.shape[axis]))
    assert reversed_slices(volume) != reversed_slices(stored)
    prob, prob_stored = localiser.probabilities(volume)[0], localiser.probabilities(stored)[0]
    assert np.array_equal(prob, prob_stored[::-1])
    found, found_stored = localiser.localise(volume), localiser.localise(stored)
    assert found.mask.sum() > 1000
    assert np.array_equal(found.mask, np.flip(found_stored.mask, axis))
    assert found.confidence == found_stored.confidence


def test_a_stack_cropped_to_the_head_before_it_is_sent_is_localised(localiser: Localiser, generated: Callable) -> None:
    """Other pipelines send stacks cut to the head (here its box and 15 mm: a field of view of about
    100 mm, padded to the network's 160 mm canvas): the brain is found in two of three such stacks
    with a Dice over 0.9."""
    from service.preprocess.localiser_inputs import MIN_GRID_PX, localiser_inputs

    scores = []
    for seed in range(3):
        volume, truth = generated(300 + seed)
        axis = int(np.argmax(volume.spacing))
        found = np.argwhere(truth)
        box = [slice(None)] * 3
        for a in range(3):
            if a != axis:
                margin = int(round(15 / volume.spacing[a]))
                box[a] = slice(max(0, found[:, a].min() - margin), found[:, a].max() + 1 + margin)
        cropped, cropped_truth = volume.region(tuple(box)), truth[tuple(box)]
        x, _ = localiser_inputs(cropped, localiser.grid_mm)
        assert min(x.shape[2:]) >= MIN_GRID_PX
        scores.append(dice(localiser.localise(cropped).mask, cropped_truth))
    assert sorted(scores)[1] > 0.9, scores


def test_a_head_at_the_edge_of_the_image_is_found_whole(localiser: Localiser, generated: Callable) -> None:
    """A stack cropped to the head's box, or whose field of view ends inside the brain, shows brain
    right up to the image's end: the network sees fluid beyond that edge, not zeros, and finds the
    brain there as it finds a whole head (zeros against the brain leave it part of the brain, or none)."""
    scores = {"box": [], "cut": []}
    for seed in range(4):
        volume, truth = generated(300 + seed)
        axis = int(np.argmax(volume.spacing))
        plane = [a for a in range(3) if a != axis]
        found = np.argwhere(truth)
        box = [slice(None)] * 3
        for a in plane:
            box[a] = slice(found[:, a].min(), found[:, a].max() + 1)
        cut = [slice(None)] * 3
        cut[plane[0]] = slice(found[:, plane[0]].min() + int(round(10 / volume.spacing[plane[0]])), None)
        for name, b in (("box", tuple(box)), ("cut", tuple(cut))):
            scores[name].append(dice(localiser.localise(volume.region(b)).mask, truth[b]))
    assert np.median(scores["box"]) > 0.85 and np.median(scores["cut"]) > 0.85, scores


def test_a_younger_fetus_is_localised_on_a_grid_that_shows_its_head_at_a_known_size(localiser: Localiser,
                                                                                     generated: Callable) -> None:
    """The generated stacks said to hold voxels 0.7 times their size: head and uterus as a younger
    pregnancy's (brains of 46-76 ml). Each brain found under SMALL_BRAIN_ML is looked at again on
    finer pixels; every stack's mask then scores over 0.9 (at the model's grid alone one of them
    held half its brain)."""
    from service.preprocess.localise import SMALL_BRAIN_ML

    scores = []
    for seed in range(4):
        volume, truth = generated(100 + seed)
        smaller = volume.affine.copy()
        smaller[:3, :3] *= 0.7
        found = localiser.localise(Volume(volume.array, smaller))
        assert found.brain_volume_ml < SMALL_BRAIN_ML
        scores.append(dice(found.mask, truth))
    assert min(scores) > 0.9, scores


def test_stacks_localised_together_get_what_each_gets_alone(localiser: Localiser) -> None:
    """The request's stacks share the network's calls (grids of two sizes, batches that cross stacks):
    every mask and confidence is what the stack gets on its own."""
    from model_export.localiser.scenes import HeadModel, synth_stack
    from tests.support.phantoms import one_fetus_scene, phantom_brain

    image, mask, affine = phantom_brain(11)
    head = HeadModel.from_arrays(image, mask, affine)
    volumes = [v for v, _ in one_fetus_scene([synth_stack(head, np.random.default_rng(200 + seed), "heldout")
                                              for seed in range(3)])]
    noise = np.random.default_rng(0).random((96, 80, 7), np.float32) * 500
    volumes.insert(1, Volume(noise, np.diag([1.2, 1.2, 3.0, 1.0])))
    assert len({localiser.probabilities(v)[0].shape[1:] for v in volumes}) > 1
    together = localiser.localise_many(volumes)
    for v, found in zip(volumes, together):
        alone = localiser.localise(v)
        assert np.array_equal(found.mask, alone.mask) and found.confidence == pytest.approx(alone.confidence, abs=1e-6)


def test_noise_is_no_brain(localiser: Localiser) -> None:
    noise = np.random.default_rng(0).random((256, 256, 30), np.float32) * 500
    found = localiser.localise(Volume(noise, np.diag([1.2, 1.2, 3.0, 1.0])))
    assert found.confidence < 0.3


@pytest.mark.skipif(not (REAL / "mial_lausanne_t30").is_dir(), reason=f"needs the real scans at {REAL}")
@pytest.mark.parametrize(("name", "floor"), [("axial1_lr", 0.88), ("coronal1_lr", 0.87), ("sagittal1_lr", 0.88)])
def test_real_scan_against_its_manual_mask(localiser: Localiser, name: str, floor: float) -> None:
    """Floors just under the shipped model's measured Dice (0.899 / 0.894 / 0.912; however the files
    store their in-plane voxels)."""
    volume = read_volume(REAL / "mial_lausanne_t30" / f"{name}.nii.gz")
    manual = read_volume(REAL / "mial_lausanne_t30" / f"{name}_brain_mask.nii.gz").array > 0
    found = localiser.localise(volume)
    assert dice(found.mask, manual) > floor
    assert found.confidence > 0.5


@pytest.mark.skipif(not (REAL / "bch_f0832s1").is_dir(), reason=f"needs the real scans at {REAL}")
def test_the_geometry_of_a_real_stack_stored_last_to_first_is_the_same(localiser: Localiser) -> None:
    """On a real whole-uterus stack the geometry itself depends on the order it walks the slices
    (`fetus_04`: 234 of 13,973 grid voxels of brain differ between the two orders of its
    probabilities; the generated phantoms' do not): the localiser walks every file's slices in one
    order, so both storages get the same brain."""
    from service.geometry.pose import index_reversal
    from service.preprocess.brain_shape import brain_from_probabilities
    from service.preprocess.stack import stack_axis

    volume = read_volume(REAL / "bch_f0832s1" / "fetus_04.nii.gz")
    axis = stack_axis(volume)
    prob, grid = localiser.probabilities(volume)
    voxel_ml = grid.grid_mm ** 2 * float(volume.spacing[axis]) / 1000.0
    walked = [brain_from_probabilities(p, voxel_ml, grid.grid_mm)[0] for p in (prob, np.ascontiguousarray(prob[::-1]))]
    assert (walked[0] != walked[1][::-1]).any()                                  # the order matters here
    stored = Volume(np.ascontiguousarray(np.flip(volume.array, axis)),
                    volume.affine @ index_reversal(axis, volume.array.shape[axis]))
    assert np.array_equal(localiser.localise(volume).mask, np.flip(localiser.localise(stored).mask, axis))


@pytest.mark.skipif(not (REAL / "bch_f0832s1").is_dir(), reason=f"needs the real scans at {REAL}")
@pytest.mark.parametrize("name", ["fetus_03", "fetus_04"])
def test_real_whole_uterus_stacks_without_masks_get_one(localiser: Localiser, name: str) -> None:
    found = localiser.localise(read_volume(REAL / "bch_f0832s1" / f"{name}.nii.gz"))
    assert 60 < found.brain_volume_ml < 700 and found.slices_with_brain >= 5 and found.confidence > 0.3


@pytest.mark.skipif(not (REAL / "bch_f0832s1").is_dir(), reason=f"needs the real scans at {REAL}")
def test_a_real_brain_leaking_into_the_fetal_body_is_cut_at_the_waist(localiser: Localiser) -> None:
    """fetus_03's brain component runs on, through one thin slice, into scattered fetal-body tissue
    over its last six slices; the geometry ends the brain before them (a waist, or the dip of the
    small slices at the component's end): at most slivers of the body are left (25-42 voxels in
    slices 38-40 against 1,100-5,200 in the brain's)."""
    found = localiser.localise(read_volume(REAL / "bch_f0832s1" / "fetus_03.nii.gz"))
    per_slice = found.mask.reshape(-1, found.mask.shape[2]).sum(0)
    assert per_slice[:38].all() and per_slice[38:].sum() < 0.01 * per_slice.sum() and not per_slice[41:].any()


def test_the_mask_is_cut_lower_than_the_region_the_pose_network_starts_from(localiser: Localiser,
                                                                            generated: Callable) -> None:
    """The localiser's mask holds its pose region and more (cut at MASK_THRESHOLD, not THRESHOLD); the
    pose network's mask is the pose region less its rim, with nothing of the mask's extra; a slice
    localised alone keeps the two cuts too."""
    from service.preprocess.brain_shape import MASK_THRESHOLD, THRESHOLD
    from service.preprocess.localisation import POSE_MASK_INSET_MM, inset_in_plane

    assert MASK_THRESHOLD < THRESHOLD
    volume, _ = generated(100)
    found = localiser.localise(volume)
    assert found.pose_region is not None and found.pose_region.any()
    assert not (found.pose_region & ~found.mask).any() and found.mask.sum() > found.pose_region.sum()
    assert np.array_equal(found.pose_mask(volume.spacing),
                          inset_in_plane(found.pose_region, volume.spacing, POSE_MASK_INSET_MM))
    k = int(np.argmax(found.mask.sum(axis=(0, 1))))
    alone = localiser.localise_slice(volume, k)
    assert not (alone.pose_region & ~alone.mask).any() and alone.mask.sum() >= alone.pose_region.sum() > 0
    assert not alone.mask[:, :, np.arange(volume.array.shape[2]) != k].any()


def test_an_upload_said_to_hold_the_csf_gets_the_localisers_inset() -> None:
    from service.pipeline.prepare import StackUpload, localise

    spacing = np.array([1.0, 1.0, 3.0])
    mask = np.zeros((40, 40, 6), np.uint8)
    mask[8:32, 8:32, 1:5] = 1
    volume = Volume(np.random.default_rng(0).random(mask.shape, np.float32), np.diag([*spacing, 1.0]))
    tight = localise(StackUpload("s.nii.gz", volume, Volume(mask, volume.affine)))
    rim = localise(StackUpload("s.nii.gz", volume, Volume(mask, volume.affine), mask_holds_csf=True))
    assert tight.method == rim.method == "mask" and tight.pose_inset_mm == 0.0 and rim.pose_inset_mm == 2.0
    assert np.array_equal(tight.pose_mask(spacing), mask > 0)
    assert rim.pose_mask(spacing)[:, :, 2].sum() == 20 * 20 and rim.report()["pose_mask_inset_mm"] == 2.0


class _ProbabilityLocaliser(Localiser):
    """A localiser whose network's probability is the stack's own value at each pixel (the grid is the
    stack's: 2.5 mm pixels, no padding)."""

    def __init__(self) -> None:
        super().__init__(None, None, 2.5, "test", "")           # type: ignore[arg-type]

    def probabilities(self, volume: Volume):  # noqa: ANN201
        from service.preprocess.localiser_inputs import LocaliserGrid
        from service.preprocess.stack import slice_images

        images, _, layout = slice_images(volume.array, volume.affine, 2)
        return images.astype(np.float32), LocaliserGrid(volume.array.shape, 2, layout, images.shape[1:], images.shape[1:],
                                                        (0, 0), 2.5)


def _streamed_face_end(order: list[int], blank: int | None = None) -> tuple[dict, dict, np.ndarray, np.ndarray]:
    """A coronal stack whose last slices hold a face larger than the frontal lobes beside it (brain in
    slices 2-15, face in 12-17, 4 pixels apart), streamed in ``order``: each slice's mask with the maps
    of the slices received before it, and alone; the brain and the face. ``blank``: a slice sent
    filled with zeros."""
    n = 20
    z = np.arange(n)[None, None, :]
    y, x = np.mgrid[0:64, 0:64]
    radius = np.where((z >= 2) & (z <= 15), 12.0 * np.sqrt(np.clip(1 - ((z - 8.5) / 8.0) ** 2, 0.05, 1)), 0.0)
    brain = np.hypot(x[..., None] - 22, y[..., None] - 32) < radius
    face = (np.abs(x[..., None] - 50) < 9) & (np.abs(y[..., None] - 32) < 14) & (z >= 12) & (z <= 17)
    assert not (ndimage.binary_dilation(brain, np.ones((9, 9, 1), bool)) & face).any()
    volume = Volume(np.where(brain | face, 0.9, 0.02).astype(np.float32), np.diag([2.5, 2.5, 3.0, 1.0]))
    if blank is not None:
        volume.array[:, :, blank] = 0.0
    localiser = _ProbabilityLocaliser()
    received: dict[int, np.ndarray] = {}
    streamed, alone = {}, {}
    for k in order:
        lo, hi = max(k - 1, 0), min(k + 1, n - 1)
        lo, hi = (lo if lo in received else k), (hi if hi in received else k)
        window = Volume(np.ascontiguousarray(volume.array[:, :, lo:hi + 1]),
                        volume.affine @ np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, lo], [0, 0, 0, 1.0]]))
        found, received[k] = localiser.slice_in_stack(window, k - lo, received, k, 3.0)
        streamed[k] = found.mask[:, :, k - lo]
        alone[k] = localiser.localise_slice(window, k - lo).mask[:, :, k - lo]
    return streamed, alone, brain, face


def test_a_streamed_slice_takes_the_region_the_stacks_brain_passes_through_not_the_face_beside_it() -> None:
    """Alone, each slice of the face end takes the face (most probability); streamed in interleaved
    order (even slices first) with the maps of the slices received before it, it takes the brain
    the stack's geometry finds. Slices of the face alone, past the brain, are judged alone."""
    n = 20
    streamed, alone, brain, face = _streamed_face_end([*range(0, n, 2), *range(1, n, 2)])
    for k in range(12, 16):                                   # the brain and the face beside it
        assert (alone[k] & face[:, :, k]).any() and not (alone[k] & brain[:, :, k]).any()
        assert (streamed[k] & brain[:, :, k]).sum() > 0.8 * brain[:, :, k].sum() and not (streamed[k] & face[:, :, k]).any()
    for k in (*range(2, 12), 16, 17):                         # the brain alone, the face alone: either way
        assert np.array_equal(streamed[k], alone[k]) and streamed[k].any()


def test_a_stack_whose_face_end_arrives_first_loses_no_brain_slice() -> None:
    """Sent from the face end (the received maps' largest object is first the face), every slice that
    shows the brain alone still gets it: where the received maps' brain (the face) does not reach a
    slice, the slice is judged alone."""
    streamed, alone, brain, face = _streamed_face_end(list(range(19, -1, -1)))
    for k in range(2, 12):
        assert (streamed[k] & brain[:, :, k]).sum() > 0.8 * brain[:, :, k].sum(), k
    assert all((streamed[k] & brain[:, :, k]).any() or not (alone[k] & brain[:, :, k]).any() for k in range(20))


def test_a_zero_filled_streamed_slice_leaves_the_stacks_brain_whole() -> None:
    """A slice sent filled with zeros in the middle of the brain gets no brain and leaves no map: the
    slices after it still find the stack's brain across it, and the face end takes the brain, not
    the face (with the blank map kept, the brain's first part alone was the received brain, which
    reaches no slice of the face end)."""
    n = 20
    streamed, _, brain, face = _streamed_face_end([*range(0, n, 2), *range(1, n, 2)], blank=10)
    assert not streamed[10].any()
    for k in range(12, 16):
        assert (streamed[k] & brain[:, :, k]).sum() > 0.8 * brain[:, :, k].sum(), k
        assert not (streamed[k] & face[:, :, k]).any(), k


def test_a_sliver_of_the_received_slices_brain_does_not_overrule_the_slice() -> None:
    """The received slices' brain (a blob in slices 0-5) reaches the new slice 6 as a sliver of 4
    pixels beside a large region of its own: the slice is judged alone and keeps that region, where
    the sliver alone would have been too small to be a brain."""
    array = np.full((48, 48, 7), 0.02, np.float32)
    array[4:20, 4:20, :6] = 0.9
    array[4:6, 4:6, 6] = 0.9                                  # what is left of the blob in slice 6
    array[26:46, 24:46, 6] = 0.9                              # the slice's own region
    volume = Volume(array, np.diag([2.5, 2.5, 3.0, 1.0]))
    localiser = _ProbabilityLocaliser()
    received = {}
    for k in range(6):
        window = Volume(np.ascontiguousarray(array[:, :, k:k + 1]),
                        volume.affine @ np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, k], [0, 0, 0, 1.0]]))
        _, received[k] = localiser.slice_in_stack(window, 0, received, k, 3.0)
    window = Volume(np.ascontiguousarray(array[:, :, 6:7]),
                    volume.affine @ np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 6], [0, 0, 0, 1.0]]))
    found, _ = localiser.slice_in_stack(window, 0, received, 6, 3.0)
    assert found.mask[26:46, 24:46, 0].all() and not found.mask[4:6, 4:6, 0].any()


@pytest.mark.parametrize("slices", [1, 5, 8, 9, 16, 22, 23, 64])
@pytest.mark.parametrize(("views", "paired"), [(1, False), (1, True), (2, True), (2, False)])
def test_a_stacks_slices_go_to_calls_of_equal_size_and_an_even_count_where_two_run_at_a_time(
        slices: int, views: int, paired: bool) -> None:
    from service.preprocess.localise import BATCH_SLICES, batch_edges

    edges = batch_edges(slices, views, paired)
    sizes = np.diff(edges)
    assert edges[0] == 0 and edges[-1] == slices and sizes.min() >= 1
    assert sizes.max() - sizes.min() <= 1 and sizes.max() <= BATCH_SLICES
    if paired and slices > 1:
        assert len(sizes) * views % 2 == 0
