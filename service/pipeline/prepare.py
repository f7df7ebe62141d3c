"""Preparing a request's stacks: each upload's mask or localised brain, N4, and its slices as the network
sees them (:func:`prepare_stacks`); :mod:`service.pipeline.predict` poses them.

Stacks with a mask go to worker threads at once; the others first through the localiser's network,
one after the other, each then settled, corrected and sliced on a worker beside the next one's
network passes.

Example (a stack with its mask, prepared without N4):
    >>> import numpy as np
    >>> from service.inference.model_file import ModelInfo
    >>> vol = Volume(np.random.default_rng(0).random((32, 32, 4), np.float32), np.diag([1.0, 1.0, 3.0, 1.0]))
    >>> box = np.zeros((32, 32, 4), np.uint8); box[8:24, 8:24] = 1
    >>> info = ModelInfo(name="m", version="0", backbone="b", label_type="anchor", input_size=32,
    ...                  pixel_spacing_mm=1.0, variance_threshold=1.0, dropout_p=0.1, atlas_id="a",
    ...                  trained_on="-", sha256="0" * 64)
    >>> [stack] = prepare_stacks([StackUpload("s.nii.gz", vol, Volume(box, vol.affine))], info, False)
    >>> stack.localisation.method, stack.prepared.inputs.shape
    ('mask', (4, 32, 32))
"""

from __future__ import annotations

import functools
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from service.consistency.stage import network_from_voxel
from service.core.cancellation import carried, checkpoint
from service.core.errors import InvalidParameter, UnusableImage
from service.inference.model_file import ModelInfo
from service.io.grids import in_order_of, on_grid
from service.io.volume import Volume
from service.preprocess.bias import n4_correct
from service.preprocess.field_of_view import cut_by_field_of_view
from service.preprocess.intensity import check_stack_values, signal_lost
from service.preprocess.localisation import Localisation, is_region_of_interest, within_region
from service.preprocess.localise import Localiser, default_localiser
from service.preprocess.localiser_inputs import LocaliserGrid, check_search
from service.preprocess.noise import input_noise
from service.preprocess.one_fetus import brain_centre_mm, one_fetus
from service.preprocess.slices import PreparedSlices, preprocess_slices
from service.preprocess.stack import StackSlices, pictures, split_stack, stack_axis

@dataclass
class StackUpload:
    """A read stack, its optional mask, and the names to report them by."""

    filename: str
    volume: Volume
    mask: Volume | None = None
    mask_filename: str | None = None
    mask_holds_csf: bool = False
    """The uploaded mask is the skull's inside (brain and extra-axial CSF), as manual fetal masks are
    usually drawn (:attr:`~service.preprocess.localisation.Localisation.holds_csf`)."""
    mask_may_be_region: bool = True
    """Whether a mask drawn rather than segmented may be a region of interest (:attr:`mask_is_region`);
    not for a stream's mask frames, which were each slice's brain as it arrived."""

    @property
    def slice_axis(self) -> int:
        """The axis the slices were acquired along: the volume's where it says (a streamed stack),
        otherwise the axis of largest spacing (:func:`~service.preprocess.stack.stack_axis`)."""
        return stack_axis(self.volume)

    @functools.cached_property
    def mask_voxels(self) -> NDArray[np.bool_] | None:
        """The uploaded mask's brain voxels (:func:`mask_voxels`), worked out once however many stages
        ask (the localisation, the request's fetus, a job's check); None without a mask."""
        return None if self.mask is None else mask_voxels(self.mask.array)

    @functools.cached_property
    def mask_is_region(self) -> bool:
        """The uploaded mask is a region of interest around the head, not a brain's outline
        (:func:`~service.preprocess.localisation.is_region_of_interest`): the localiser finds the brain in it."""
        return self.mask_may_be_region and self.mask_voxels is not None and is_region_of_interest(self.mask_voxels,
                                                                                            self.mask.spacing)

    @property
    def region(self) -> NDArray[np.bool_] | None:
        """The region of interest the localiser searches (:attr:`mask_is_region`), else None."""
        return self.mask_voxels if self.mask_is_region else None

    @property
    def localised(self) -> bool:
        """The localiser finds this stack's brain: it came without a mask, or with a region around the head."""
        return self.mask is None or self.mask_is_region

    def kept_to_region(self, found: Localisation) -> Localisation:
        """The localiser's ``found`` brain, kept to the uploaded region where there is one."""
        return found if self.region is None else within_region(found, self.region, self.volume.spacing)


def mask_voxels(array: NDArray) -> NDArray[np.bool_]:
    """The voxels an uploaded mask marks: every nonzero voxel of a mask of whole numbers (0 / 1,
    0 / 255, a label map; -1 where a mask of 255 was saved as signed bytes), and of a mask of
    fractions (a probability map, a mask resampled with partial volumes) those at half its largest
    magnitude or more: a probability map's faint background is not brain, nor the blur a resampled
    mask's edge gains.

    Example (a binary mask as floats, a signed one, and a probability map with a faint background):
        >>> mask_voxels(np.array([0.0, 255.0, 255.0])).tolist(), mask_voxels(np.array([0, -1, -1], np.int8)).tolist()
        ([False, True, True], [False, True, True])
        >>> mask_voxels(np.array([0.02, 0.3, 0.9, 1.0])).tolist()
        [False, False, True, True]
    """
    a = np.asarray(array)
    if a.dtype.kind in "biu":
        return a != 0
    a = np.where(np.isfinite(a), a, 0.0)
    if not a.size or np.array_equal(a, np.round(a)):
        return a != 0
    return np.abs(a) >= 0.5 * float(np.abs(a).max())


@dataclass
class PreparedStack:
    upload: StackUpload
    slices: StackSlices
    prepared: PreparedSlices
    localisation: Localisation
    timings: dict[str, float] = field(default_factory=dict)
    input_noise: float = float("nan")
    """The noise of the network's inputs (:func:`~service.preprocess.noise.input_noise`; NaN: not measured)."""

    @functools.cached_property
    def signal_lost(self) -> NDArray[np.bool_]:
        """``[n]`` the slices whose brain lost its signal (:func:`~service.preprocess.intensity.signal_lost`,
        on the bias-corrected slices and their pose masks): they take no part in image consistency."""
        return signal_lost(self.slices.images, self.slices.masks)

    @functools.cached_property
    def cut_by_field_of_view(self) -> NDArray[np.bool_]:
        """``[n]`` the slices whose brain runs out of the picture in their plane
        (:func:`~service.preprocess.field_of_view.cut_by_field_of_view`, on the localisation's brain
        region; where it holds the CSF around the brain, a cut as deep as the pose network's mask's
        inset takes the CSF alone): the network sees part of a brain. The
        stages treat them as any other slice (the images of their crossings still relate them to
        the others); the answer names them, so that a user knows why their poses may be off and that
        a larger field of view avoids it."""
        masks = pictures(self.localisation.brain_region, self.slices.slice_axis, self.slices.layout)
        return cut_by_field_of_view(masks, self.slices.pixel_mm, self.localisation.pose_inset_mm)

    def network_from_voxel(self) -> np.ndarray:
        """``[n, 4, 4]`` voxel ``(i, j, k)`` of slice ``k`` -> its network frame (the service's crop/centre)."""
        return network_from_voxel(self.prepared.input_from_network(), self.slices.slice_from_voxel)

    def in_network_frame(self, atlas_from_voxel: NDArray) -> NDArray[np.float64]:
        """Slice poses ``atlas_from_voxel [n, 4, 4]`` of this stack's slices (an answer's, or a
        simulation's truth) as the network gives them: its frame -> atlas mm, through the service's
        crop and centring (what a training label and an evaluation compare)."""
        return np.asarray(atlas_from_voxel, np.float64) @ np.linalg.inv(self.network_from_voxel())


def mask_on_stack_grid(upload: StackUpload) -> StackUpload:
    """``upload`` with its mask's voxels in its stack's order, where the mask's file holds the stack's
    voxels (the same voxel centres in the world) stored in another order: axes swapped or reversed,
    as a tool that reorients its files to a standard orientation writes them (nibabel's orientation
    tools, as the client's :func:`~client.scanner_stack.in_stack_order`). Any other mask is left as
    it is, for :func:`check_mask_grid` to refuse.

    Example (the mask stored with its first axis reversed, its header saying so):
        >>> from service.geometry.pose import index_reversal
        >>> stack = Volume(np.zeros((3, 2, 2), np.float32), np.diag([1.0, 1.0, 3.0, 1.0]))
        >>> m = np.zeros((3, 2, 2), np.uint8); m[0] = 1                  # the stack's first row of voxels
        >>> flipped = Volume(m[::-1].copy(), np.diag([1.0, 1.0, 3.0, 1.0]) @ index_reversal(0, 3))
        >>> mask_on_stack_grid(StackUpload("s.nii.gz", stack, flipped)).mask.array[:, 0, 0].tolist()
        [1, 0, 0]
    """
    mask = upload.mask
    ordered = None if mask is None else in_order_of(mask, upload.volume)
    return upload if ordered is None or ordered is mask else replace(upload, mask=ordered)


def check_mask_grid(upload: StackUpload) -> None:
    """The mask must be on exactly the stack's grid (shape and voxel -> world map).

    Every corner of the grid is compared: a mask stored with two axes swapped (a square grid read
    the other way round) keeps two opposite corners where its stack has them, and only the others
    show that its voxels are not the stack's.

    Example (the stack's first two axes swapped in the mask's file, the same world points):
        >>> stack = Volume(np.zeros((4, 4, 2), np.float32), np.diag([1.0, 1.0, 3.0, 1.0]))
        >>> swapped = Volume(np.zeros((4, 4, 2), np.uint8), np.diag([1.0, 1.0, 3.0, 1.0])[:, [1, 0, 2, 3]])
        >>> check_mask_grid(StackUpload("s.nii.gz", stack, swapped, "m.nii.gz"))
        Traceback (most recent call last):
        ...
        service.core.errors.UnusableImage: masks: m.nii.gz is not on the grid of its stack s.nii.gz (different origin, spacing or orientation)
    """
    if upload.mask is None:
        return
    name = upload.mask_filename or "mask"
    if upload.mask.array.shape != upload.volume.array.shape:
        raise UnusableImage(f"masks: {name} has shape {list(upload.mask.array.shape)} but its stack "
                            f"{upload.filename} has {list(upload.volume.array.shape)}")
    if not on_grid(upload.mask.affine, upload.volume):
        raise UnusableImage(f"masks: {name} is not on the grid of its stack {upload.filename} "
                            "(different origin, spacing or orientation)")


MAX_MASK_ML = 2500.0
"""The most an uploaded mask may mark (ml): more than the head of a fetus at term holds, a
hydrocephalic one's too. A mask of more is not a brain's (the body's, the uterus's, a field of view
of ones) and would make every later step work on the whole image."""


def check_mask_volume(upload: StackUpload) -> None:
    """422 naming the mask where it marks more than :data:`MAX_MASK_ML`.

    Example (a mask of ones over a 400 x 400 x 100 mm field of view):
        >>> stack = Volume(np.zeros((100, 100, 25), np.float32), np.diag([4.0, 4.0, 4.0, 1.0]))
        >>> check_mask_volume(StackUpload("s.nii.gz", stack, Volume(np.ones((100, 100, 25), np.uint8), stack.affine),
        ...                               "m.nii.gz"))
        Traceback (most recent call last):
        ...
        service.core.errors.UnusableImage: masks: m.nii.gz marks 16000 ml, more than a fetal head holds (2500 ml at most): send a mask of the fetal brain or a box around its head (not of the body or the field of view), or none
    """
    marked_ml = marked_volume_mm3(upload) / 1000.0
    if marked_ml > MAX_MASK_ML:
        raise UnusableImage(f"masks: {upload.mask_filename or 'mask'} marks {marked_ml:.0f} ml, more than a fetal head "
                            f"holds ({MAX_MASK_ML:.0f} ml at most): send a mask of the fetal brain or a box around its "
                            "head (not of the body or the field of view), or none")


def marked_volume_mm3(upload: StackUpload) -> float:
    """What the uploaded mask marks, mm³ (0 without a mask)."""
    marked = upload.mask_voxels
    return 0.0 if marked is None else float(np.count_nonzero(marked)) * float(np.prod(upload.mask.spacing))


def marked_brain(upload: StackUpload) -> tuple[float, NDArray[np.float64]]:
    """What the uploaded mask marks: its volume (mm³) and the extent (mm, along the scanner's axes) of
    its voxels, each a box half a voxel about its centre; zeros where there is no mask or it marks
    no voxel.

    Example (a block of 10 x 20 x 5 voxels of 1 x 1 x 3 mm):
        >>> mask = np.zeros((30, 30, 10), np.uint8)
        >>> mask[5:15, 5:25, 2:7] = 1
        >>> v = Volume(mask.astype(np.float32), np.diag([1.0, 1.0, 3.0, 1.0]))
        >>> volume, extent = marked_brain(StackUpload("s.nii.gz", v, Volume(mask, v.affine), "m.nii.gz"))
        >>> volume, extent.tolist()
        (3000.0, [10.0, 20.0, 15.0])
    """
    marked = upload.mask_voxels
    if marked is None or not marked.any():
        return 0.0, np.zeros(3)
    linear = np.asarray(upload.mask.affine, np.float64)[:3, :3]
    # Along a row of the last axis a scanner coordinate is monotone: its first and last marked voxels
    # bound the row's, so they alone are placed (not every voxel of a mask of millions).
    i, j = np.nonzero(marked.any(axis=2))
    first = np.argmax(marked, axis=2)[i, j]
    last = marked.shape[2] - 1 - np.argmax(marked[:, :, ::-1], axis=2)[i, j]
    ends = np.concatenate([np.stack([i, j, first], axis=1), np.stack([i, j, last], axis=1)])
    centres = ends @ linear.T                                    # the offset cancels in an extent
    voxel_reach = np.abs(linear).sum(axis=1)                     # one voxel's extent along each scanner axis
    return marked_volume_mm3(upload), centres.max(axis=0) - centres.min(axis=0) + voxel_reach


def check_distinct_stacks(uploads: list[StackUpload]) -> None:
    """400 naming both files where a request sends one stack twice (the same grid and voxels under two
    names, stored in the same voxel order or another: :func:`in_order_of`): the stages would take
    the copy for a second acquisition that agrees with the first and
    answer surer than the scan allows (or, for two copies alone, with nothing crossing them, accept
    none).

    Example:
        >>> v = Volume(np.zeros((4, 4, 3), np.float32), np.eye(4))
        >>> check_distinct_stacks([StackUpload("a", v), StackUpload("b", Volume(v.array + 1, v.affine))])
        >>> check_distinct_stacks([StackUpload("a", v), StackUpload("b", Volume(v.array.copy(), v.affine))])
        Traceback (most recent call last):
        ...
        service.core.errors.InvalidParameter: stacks: b is the same image as a (the same grid and voxels): send each stack of a scan once
    """
    for j, b in enumerate(uploads):
        for a in uploads[:j]:
            same_grid = in_order_of(b.volume, a.volume)             # however either file stores its voxels
            if same_grid is not None and np.array_equal(a.volume.array, same_grid.array):
                raise InvalidParameter(f"stacks: {b.filename} is the same image as {a.filename} (the same grid and "
                                       "voxels): send each stack of a scan once")


def localise(upload: StackUpload, localiser: Localiser | None = None) -> Localisation:
    """The uploaded mask (its confidence 1, or 0 where it marks no voxel: the user says the stack
    shows no brain), else the brain that ``localiser`` (default: the shipped one) finds."""
    if not upload.localised:
        voxels = upload.mask_voxels
        return Localisation.of(voxels, upload.volume.spacing, "mask", float(voxels.any()), upload.mask_holds_csf)
    return upload.kept_to_region((localiser or default_localiser()).localise(upload.volume, upload.region))


def prepare_stack(upload: StackUpload, info: ModelInfo, bias_correction: bool,
                  localiser: Localiser | None = None, found: tuple[Localisation, float] | None = None) -> PreparedStack:
    """Localise, bias-correct, split and preprocess one stack (runs in a worker thread); ``found``:
    its localisation and the seconds it took, where the caller localised it already."""
    checkpoint()
    timings: dict[str, float] = {}
    vol = upload.volume
    t = time.perf_counter()
    localisation = found[0] if found is not None else localise(upload, localiser)
    mask = localisation.mask
    timings["localisation"] = found[1] if found is not None else time.perf_counter() - t
    checkpoint()
    t = time.perf_counter()
    array = n4_correct(vol, mask) if bias_correction and mask.any() else vol.array
    timings["bias_correction"] = time.perf_counter() - t
    t = time.perf_counter()
    slices = split_stack(Volume(array, vol.affine), localisation.pose_mask(vol.spacing, upload.slice_axis), upload.slice_axis)
    prepared = preprocess_slices(slices.images, slices.masks, slices.pixel_mm, info.input_size, info.pixel_spacing_mm)
    noise = input_noise(slices.images, slices.masks, slices.pixel_mm, info.pixel_spacing_mm)
    timings["preprocess"] = time.perf_counter() - t
    return PreparedStack(upload, slices, prepared, localisation, timings, noise)


def localise_uploads(uploads: list[StackUpload], localiser: Localiser | None = None) -> list[Localisation]:
    """Each upload's localisation: its mask, else the brain ``localiser`` (default: the shipped one)
    finds, the uploads without a mask in shared network calls
    (:meth:`~service.preprocess.localise.Localiser.localise_many`), on the fetus the masks show."""
    missing = [u for u in uploads if u.localised]
    found = iter((localiser or default_localiser()).localise_many([u.volume for u in missing], mask_centres(uploads),
                                                                  [u.region for u in missing]) if missing else [])
    return [u.kept_to_region(next(found)) if u.localised else localise(u) for u in uploads]


def mask_centres(uploads: list[StackUpload]) -> list[np.ndarray]:
    """The centres (scanner mm) of the uploaded masks' brains: where the user's fetus is."""
    centres = [brain_centre_mm(u.mask_voxels, u.volume.affine) for u in uploads if u.mask is not None]
    return [c for c in centres if c is not None]


def check_uploads(uploads: list[StackUpload]) -> None:
    """The checks of a request's stacks that need no stage (4xx naming what is wrong): each mask on its
    stack's grid and of a brain's volume, no stack sent twice, no mask sent as a stack, and the
    localiser's search within its bound; a job's submission makes them before it is queued,
    :func:`prepare_stacks` where it runs."""
    check_stack_values([(u.filename, u.volume.array) for u in uploads])
    for u in uploads:
        check_mask_grid(u)
        check_mask_volume(u)
    check_distinct_stacks(uploads)
    check_search([(u.filename, u.volume) for u in uploads if u.localised])


def prepare_stacks(uploads: list[StackUpload], info: ModelInfo, bias_correction: bool,
                   workers: int = 2, localiser: Localiser | None = None) -> list[PreparedStack]:
    """:func:`prepare_stack` for every stack, ``workers`` stacks at a time (N4 releases the GIL).

    The stacks without a mask (or with a region of interest around the head,
    :attr:`StackUpload.mask_is_region`) go through ``localiser``'s network (default: the shipped one) one
    after the other, here; each goes on to the workers as soon as its probabilities are there, so
    that its geometry, N4 and slices are worked out beside the next stack's network passes (the
    network runs on both cores, the rest mostly on one). Stacks with a mask start at once. Where the
    stacks settled on brains farther apart than a fetus moves (twins), they settle again on one
    fetus's (:func:`~service.preprocess.one_fetus.one_fetus`: the uploaded masks', or the one most
    of them see) and are prepared again."""
    check_uploads(uploads)
    with ThreadPoolExecutor(max_workers=max(1, min(workers, len(uploads)))) as pool:
        futures = [None if u.localised else pool.submit(carried(prepare_stack), u, info, bias_correction)
                   for u in uploads]
        settling = {}
        for i, u in enumerate(uploads):
            if u.localised:
                checkpoint()
                loc = localiser or default_localiser()
                t = time.perf_counter()
                probabilities = loc.probabilities(u.volume)
                settling[i] = pool.submit(carried(_settle_and_prepare), u, info, bias_correction, loc, probabilities,
                                          time.perf_counter() - t)
        prepared = [None if f is None else f.result() for f in futures]
        found = {}
        for i, f in settling.items():
            prepared[i], found[i] = f.result()
    if found and len(uploads) > 1:                      # every stack on one fetus's brain (twins)
        which = sorted(found)
        again = one_fetus(localiser or default_localiser(), [uploads[i].volume for i in which],
                          [found[i] for i in which], [prepared[i].localisation for i in which], mask_centres(uploads))
        for i, localisation in zip(which, again):
            if localisation is not prepared[i].localisation:
                prepared[i] = prepare_stack(uploads[i], info, bias_correction,
                                            found=(uploads[i].kept_to_region(localisation),
                                                   prepared[i].timings["localisation"]))
    return prepared


def _settle_and_prepare(upload: StackUpload, info: ModelInfo, bias_correction: bool, localiser: Localiser,
                        found: tuple[np.ndarray, LocaliserGrid], seconds: float,
                        ) -> tuple[PreparedStack, tuple[np.ndarray, LocaliserGrid]]:
    """:func:`prepare_stack` of a stack whose localiser probabilities ``found`` took ``seconds``: its
    brain settled (:meth:`~service.preprocess.localise.Localiser.settle_closer`: a small brain seen
    again on finer pixels), then the rest; with the probabilities the brain rests on."""
    t = time.perf_counter()
    localisation, found = localiser.settle_closer(upload.volume, *found, upload.region)
    localisation = upload.kept_to_region(localisation)
    return prepare_stack(upload, info, bias_correction, found=(localisation, seconds + time.perf_counter() - t)), found
