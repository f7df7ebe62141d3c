"""A request's stack as uploaded (:class:`StackUpload`: the stack, its optional mask and their names)
and the checks of a request's stacks that need no stage (:func:`check_uploads`): each mask on its
stack's grid and of a brain's volume, no stack sent twice, no mask sent as a stack, the localiser's
search within its bound. A job's submission makes them before it is queued,
:func:`~service.pipeline.prepare.prepare_stacks` where it runs.

Example (a mask of the stack's grid, and one stack sent twice):
    >>> v = Volume(np.random.default_rng(0).random((8, 8, 3), np.float32), np.diag([1.0, 1.0, 3.0, 1.0]))
    >>> box = np.zeros((8, 8, 3), np.uint8); box[2:6, 2:6] = 1
    >>> check_uploads([StackUpload("s.nii.gz", v, Volume(box, v.affine), "m.nii.gz")])
    >>> check_uploads([StackUpload("a.nii.gz", v), StackUpload("b.nii.gz", v)])
    Traceback (most recent call last):
    ...
    service.core.errors.InvalidParameter: stacks: b.nii.gz is the same image as a.nii.gz (the same grid, and voxels the same up to a scale and an offset): send each stack of a scan once
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from service.core.errors import InvalidParameter, UnusableImage
from service.io.grids import in_order_of, on_grid
from service.io.volume import Volume
from service.preprocess.intensity import SAMPLED_VOXELS, check_stack_values
from service.preprocess.localisation import Localisation, is_region_of_interest, within_region
from service.preprocess.localiser_inputs import check_search
from service.preprocess.stack import stack_axis


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


SAME_IMAGE_CORRELATION = 1 - 2e-5
"""Two stacks on one grid whose voxels correlate this closely are one image (a copy rescaled, or
requantised: 1 - 1e-5 for 8 bits); two acquisitions of a fetus on one planning differ by its motion
and their noise (for noise alone, 1 - 1e-3 at a signal-to-noise ratio of 30, 1 - 8e-5 at 100)."""


def check_distinct_stacks(uploads: list[StackUpload]) -> None:
    """400 naming both files where a request sends one stack twice (the same grid and voxels under two
    names, stored in the same voxel order or another: :func:`in_order_of`, their values the same or
    the same up to a scale and an offset: :func:`same_image`): the stages would take
    the copy for a second acquisition that agrees with the first and
    answer surer than the scan allows (or, for two copies alone, with nothing crossing them, accept
    none).

    Example:
        >>> v = Volume(np.random.default_rng(0).random((4, 4, 3), np.float32), np.eye(4))
        >>> check_distinct_stacks([StackUpload("a", v), StackUpload("b", Volume(v.array[::-1].copy(), v.affine))])
        >>> check_distinct_stacks([StackUpload("a", v), StackUpload("b", Volume(v.array * 1000 + 3, v.affine))])
        Traceback (most recent call last):
        ...
        service.core.errors.InvalidParameter: stacks: b is the same image as a (the same grid, and voxels the same up to a scale and an offset): send each stack of a scan once
    """
    for j, b in enumerate(uploads):
        for a in uploads[:j]:
            same_grid = in_order_of(b.volume, a.volume)             # however either file stores its voxels
            if same_grid is not None and same_image(a.volume.array, same_grid.array):
                raise InvalidParameter(f"stacks: {b.filename} is the same image as {a.filename} (the same grid, and "
                                       "voxels the same up to a scale and an offset): send each stack of a scan once")


def same_image(a: NDArray, b: NDArray) -> bool:
    """Whether two arrays of one shape hold the same values, or the same up to a positive scale and an
    offset (correlation :data:`SAME_IMAGE_CORRELATION` or more). A strided sample of
    :data:`~service.preprocess.intensity.SAMPLED_VOXELS` voxels decides two different images first; the
    whole arrays are compared in chunks only where it does not.

    Example:
        >>> x = np.arange(12.0).reshape(3, 4)
        >>> same_image(x, x), same_image(x, 0.37 * x + 1000), same_image(x, -x), same_image(x, np.zeros_like(x))
        (True, True, False, False)
    """
    if np.array_equal(a, b):
        return True
    x, y = np.asarray(a).reshape(-1), np.asarray(b).reshape(-1)
    step = max(1, x.size // SAMPLED_VOXELS)
    return correlation(x[::step], y[::step]) >= SAME_IMAGE_CORRELATION and correlation(x, y) >= SAME_IMAGE_CORRELATION


def correlation(x: NDArray, y: NDArray, chunk: int = 1 << 20) -> float:
    """Pearson correlation of two flat arrays (0 where either is constant), their sums in float64 over
    chunks of ``chunk`` values: no float64 copy of a whole stack."""
    n = x.size
    mx, my = (float(np.mean(v, dtype=np.float64)) for v in (x, y))
    sxx = syy = sxy = 0.0
    for start in range(0, n, chunk):
        u = x[start:start + chunk].astype(np.float64) - mx
        v = y[start:start + chunk].astype(np.float64) - my
        sxx, syy, sxy = sxx + float(u @ u), syy + float(v @ v), sxy + float(u @ v)
    scale = float(np.sqrt(sxx * syy))
    return sxy / scale if scale > 0 else 0.0


def check_uploads(uploads: list[StackUpload]) -> None:
    """The checks of a request's stacks that need no stage (4xx naming what is wrong): each mask on its
    stack's grid and of a brain's volume, no stack sent twice, no mask sent as a stack, and the
    localiser's search within its bound; a job's submission makes them before it is queued,
    :func:`~service.pipeline.prepare.prepare_stacks` where it runs."""
    check_stack_values([(u.filename, u.volume.array) for u in uploads])
    for u in uploads:
        check_mask_grid(u)
        check_mask_volume(u)
    check_distinct_stacks(uploads)
    check_search([(u.filename, u.volume) for u in uploads if u.localised])
