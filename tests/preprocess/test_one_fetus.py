"""One fetus per request: stacks of a twin pregnancy settle on the same fetus's brain."""

from __future__ import annotations

import numpy as np

from service.inference.model_file import ModelInfo
from service.io.volume import Volume
from service.pipeline.prepare import StackUpload, prepare_stacks
from service.preprocess.localise import Localiser
from service.preprocess.localiser_inputs import LocaliserGrid
from service.preprocess.one_fetus import brain_centre_mm
from service.preprocess.stack import slice_images

GRID_MM = 2.5


class _ProbabilityLocaliser(Localiser):
    """A localiser whose network's probability is the stack's own value (the stack on the network's
    grid: 64 x 64 pixels of 2.5 mm, slices along the last axis)."""

    def __init__(self) -> None:
        super().__init__(None, None, GRID_MM, "test", "")           # type: ignore[arg-type]

    def probabilities(self, volume: Volume):  # noqa: ANN201
        return self.probabilities_of([volume])[0]

    def probabilities_of(self, volumes: list[Volume], grids_mm: list[float] | None = None):  # noqa: ANN201
        out = []
        for v in volumes:                            # the stack's own pixels, laid out as the localiser's
            images, _, layout = slice_images(v.array, v.affine, 2)
            out.append((images.astype(np.float32),
                        LocaliserGrid(v.array.shape, 2, layout, images.shape[1:], images.shape[1:], (0, 0), GRID_MM)))
        return out


def _again(volume: Volume) -> Volume:
    """The same scene acquired again, with its own noise: a stack of its own (a request refuses one stack
    sent twice, rescaled or not)."""
    noise = np.random.default_rng(0).normal(0.0, 0.02, volume.array.shape).astype(np.float32)
    return Volume(np.clip(volume.array + noise, 0.0, 1.0), volume.affine)


def _twins(larger: str, slices: int = 20) -> Volume:
    """A stack of two heads 100 mm apart (balls of 30 mm radius in scanner mm, 10 slices from the
    first), the ``larger`` one ("first" or "second") holding more probability."""
    affine = np.diag([GRID_MM, GRID_MM, 4.0, 1.0])
    affine[:3, 3] = (-80.0, -80.0, -40.0)
    index = np.stack(np.meshgrid(np.arange(64), np.arange(64), np.arange(slices), indexing="ij"), axis=-1)
    world = index @ affine[:3, :3].T + affine[:3, 3]
    first = np.linalg.norm(world - [-40.0, 0.0, 0.0], axis=-1) < 30.0
    second = np.linalg.norm(world - [60.0, 0.0, 0.0], axis=-1) < (33.0 if larger == "second" else 27.0)
    return Volume(np.where(first, 0.9, np.where(second, 0.95, 0.0)).astype(np.float32), affine)


def test_the_stacks_of_a_twin_pregnancy_settle_on_the_brain_most_of_them_see() -> None:
    """Two stacks see the first fetus's brain as the brain, the third the second fetus's: alone, each
    keeps its own; as one request, all three the first (the third's second brain left out of its
    choice), whether localised together or prepared for ``/v1/predict``."""
    localiser = _ProbabilityLocaliser()
    volumes = [_twins("first"), _again(_twins("first")), _twins("second")]
    alone = [localiser.settle(v, *localiser.probabilities(v)) for v in volumes]
    centres = [brain_centre_mm(found.mask, v.affine) for found, v in zip(alone, volumes)]
    assert centres[0][0] < -20 and centres[2][0] > 40                  # the third alone: the second fetus
    together = localiser.localise_many(volumes)
    assert all(brain_centre_mm(found.mask, v.affine)[0] < -20 for found, v in zip(together, volumes))
    info = ModelInfo(name="m", version="0", backbone="b", label_type="anchor", input_size=32, pixel_spacing_mm=2.0,
                     variance_threshold=1.0, dropout_p=0.1, atlas_id="a", trained_on="-", sha256="0" * 64)
    prepared = prepare_stacks([StackUpload(f"s{i}.nii.gz", v) for i, v in enumerate(volumes)], info, False,
                              localiser=localiser)
    assert all(brain_centre_mm(p.localisation.mask, v.affine)[0] < -20 for p, v in zip(prepared, volumes))


def test_an_uploaded_masks_brain_decides_which_fetus() -> None:
    """One stack comes with a mask on the second fetus: the stacks without masks settle there too."""
    localiser = _ProbabilityLocaliser()
    volumes = [_twins("first"), _again(_twins("first")), _twins("second")]
    mask = Volume((volumes[2].array > 0.92).astype(np.uint8), volumes[2].affine)
    uploads = [StackUpload("a.nii.gz", volumes[0]), StackUpload("b.nii.gz", volumes[1]),
               StackUpload("c.nii.gz", volumes[2], mask, "c_mask.nii.gz")]
    info = ModelInfo(name="m", version="0", backbone="b", label_type="anchor", input_size=32, pixel_spacing_mm=2.0,
                     variance_threshold=1.0, dropout_p=0.1, atlas_id="a", trained_on="-", sha256="0" * 64)
    prepared = prepare_stacks(uploads, info, False, localiser=localiser)
    assert all(brain_centre_mm(p.localisation.mask, v.affine)[0] > 40 for p, v in zip(prepared, volumes))


def test_a_stack_stored_last_to_first_settles_on_the_same_fetus() -> None:
    """The third stack's file stores its slices last to first (its heads near its last slices, not
    its first): the geometry sees them in the scanner's order, and the pixels near the request's
    fetus (``prefer``) with them, so it settles on the first fetus as the same stack stored first to
    last does (were ``prefer`` left in the file's order, it would lie 19 slices from that fetus's
    brain, which would not reach it, and the stack would keep the second fetus's)."""
    from service.geometry.pose import index_reversal
    from service.preprocess.localise import reversed_slices

    localiser = _ProbabilityLocaliser()
    plain = _twins("second", slices=40)
    stored = Volume(np.ascontiguousarray(plain.array[:, :, ::-1]), plain.affine @ index_reversal(2, 40))
    assert reversed_slices(stored) and not reversed_slices(plain)
    answers = [localiser.localise_many([_twins("first"), _twins("first"), third])[2] for third in (plain, stored)]
    assert brain_centre_mm(answers[1].mask, stored.affine)[0] < -20
    assert np.array_equal(answers[0].mask, answers[1].mask[:, :, ::-1])


def test_stacks_of_one_fetus_are_left_as_they_settled() -> None:
    localiser = _ProbabilityLocaliser()
    volumes = [_twins("first"), _twins("first")]
    alone = [localiser.settle(v, *localiser.probabilities(v)) for v in volumes]
    together = localiser.localise_many(volumes)
    assert all(np.array_equal(a.mask, b.mask) and a.confidence == b.confidence for a, b in zip(alone, together))


def test_a_stack_that_sees_no_brain_where_the_others_do_keeps_its_own() -> None:
    """A fetus that moved farther than :data:`BRAIN_MOVE_MM` between stacks: the stack whose only
    brain lies there keeps it (there is none near the others' for it to take)."""
    localiser = _ProbabilityLocaliser()
    volumes = [_twins("first"), _again(_twins("first")), _twins("second")]
    volumes[2].array[volumes[2].array == np.float32(0.9)] = 0.0         # the third sees the second head alone
    alone = localiser.settle(volumes[2], *localiser.probabilities(volumes[2]))
    together = localiser.localise_many(volumes)
    assert together[2].brain_volume_ml > 0 and np.array_equal(together[2].mask, alone.mask)


def test_the_pixels_near_the_fetus_are_those_near_it_in_the_scanner() -> None:
    """An oblique stack (1.1 mm pixels, 3.3 mm slices, turned about all three axes): the localiser
    grid's pixels that :func:`near_on_grid` marks, brought back onto the stack's grid
    (:meth:`LocaliserGrid.to_stack`), are its voxels within :data:`CENTRE_REACH_MM` of the centre in
    scanner mm, to a grid pixel (2.5 mm) and a slice's half-thickness."""
    from scipy.spatial.transform import Rotation

    from service.preprocess.localiser_inputs import localiser_inputs
    from service.preprocess.one_fetus import CENTRE_REACH_MM, near_on_grid

    affine = np.eye(4)
    affine[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix() @ np.diag([1.1, 1.1, 3.3])
    affine[:3, 3] = (-120.0, 40.0, -30.0)
    volume = Volume(np.ones((150, 130, 24), np.float32), affine)
    centre = affine[:3, :3] @ [80.0, 60.0, 11.0] + affine[:3, 3]
    _, grid = localiser_inputs(volume, GRID_MM)
    back = grid.to_stack(near_on_grid(volume, grid, centre).astype(np.float32)) > 0.5
    index = np.stack(np.meshgrid(*[np.arange(n) for n in volume.array.shape], indexing="ij"), axis=-1)
    distance = np.linalg.norm(index @ affine[:3, :3].T + affine[:3, 3] - centre, axis=-1)
    slack = GRID_MM + 3.3 / 2
    assert back[distance <= CENTRE_REACH_MM - slack].all()
    assert not back[distance > CENTRE_REACH_MM + slack].any()


def test_a_brains_centre_is_the_mean_of_its_voxels_in_scanner_mm() -> None:
    """From the mask's counts along each axis: the mean of its voxels' positions, on an oblique grid."""
    rng = np.random.default_rng(3)
    mask = rng.random((30, 20, 12)) > 0.8
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    affine = np.eye(4)
    affine[:3, :3], affine[:3, 3] = q @ np.diag([0.7, 0.9, 3.3]), [-40.0, 12.5, 80.0]
    voxels = np.argwhere(mask)
    expected = (affine[:3, :3] @ voxels.T).T.mean(axis=0) + affine[:3, 3]
    np.testing.assert_allclose(brain_centre_mm(mask, affine), expected, atol=1e-9)
    assert brain_centre_mm(np.zeros((3, 3, 3), bool), affine) is None
