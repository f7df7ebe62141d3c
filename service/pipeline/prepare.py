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
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from service.consistency.stage import network_from_voxel
from service.core.cancellation import carried, checkpoint
from service.inference.model_file import ModelInfo
from service.io.volume import Volume
from service.pipeline.stack_upload import StackUpload, check_uploads
from service.preprocess.bias import n4_correct
from service.preprocess.field_of_view import cut_by_field_of_view
from service.preprocess.intensity import signal_lost
from service.preprocess.localisation import Localisation
from service.preprocess.localise import Localiser, default_localiser
from service.preprocess.localiser_inputs import LocaliserGrid
from service.preprocess.noise import input_noise
from service.preprocess.one_fetus import brain_centre_mm, one_fetus
from service.preprocess.slices import PreparedSlices, preprocess_slices
from service.preprocess.stack import StackSlices, pictures, split_stack


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
