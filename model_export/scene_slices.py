"""Pose-network training slices cut with the localiser's own masks, from generated whole-uterus scenes.

The pose network learns on slices of the skull-stripped atlases, masked by the atlas's brain mask
made a little imperfect (:mod:`model_export.simulate`). A stack sent without a mask is cut instead
with the learned localiser's mask: the skull's inside, less a rim (:data:`~service.preprocess.localisation.POSE_MASK_INSET_MM`),
whose outline differs from the atlas's in ways no perturbation of that mask draws (a face's edge
kept, a lobe's tip lost, CSF left in), and the network reads a slice's pose partly off its
outline. Here a generated whole-uterus scene (:func:`~model_export.localiser.scenes.synth_scene`,
the head rigid at the atlas's size, so every slice's true atlas pose is known) goes through
``/v1/predict``'s own preparation of a stack without a mask: the localiser, the pose mask, the
slices, the crop and centring (:func:`~service.pipeline.prepare.prepare_stacks`, without N4: the
simulated training slices keep their bias field too). Each slice the service would pose becomes a
network input whose label is its true pose: its network frame -> atlas mm, as the stream's labels
are given.

A scene costs about 2.5 s on one core (the scene itself 1-3 s, the localiser and the slices 0.4 s)
and gives about 20 slices, where the plain simulation gives about 200 slices a second, so a
training worker keeps a few scenes (:class:`ScenePool`) and draws each slice several times before
its scene is replaced.

Example (needs the atlas volumes; a phantom head stands in):
    >>> import numpy as np                                                            # doctest: +SKIP
    >>> from tests.support.phantoms import phantom_brain                              # doctest: +SKIP
    >>> head = HeadModel.from_arrays(*phantom_brain(11))                              # doctest: +SKIP
    >>> batch = scene_slices(head, np.random.default_rng(0), default_localiser(), 96, 1.25)  # doctest: +SKIP
    >>> batch.inputs.shape[1:], batch.poses.shape[1:]                                 # doctest: +SKIP
    ((96, 96), (4, 4))
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from model_export.localiser.scenes import HeadModel, synth_scene
from model_export.simulate import SliceBatch
from service.inference.acceptance import MIN_MASK_FRACTION
from service.inference.model_file import ModelInfo
from service.pipeline.prepare import StackUpload, prepare_stacks
from service.preprocess.localise import Localiser


def model_grid(size: int, pixel_mm: float) -> ModelInfo:
    """What :func:`prepare_stacks` reads of a model: its input grid (``size`` pixels of ``pixel_mm``)."""
    return ModelInfo(name="training", version="0", backbone="-", label_type="-", input_size=size,
                     pixel_spacing_mm=pixel_mm, variance_threshold=0.0, dropout_p=0.0, atlas_id="-",
                     trained_on="-", sha256="0" * 64)


def scene_slices(head: HeadModel, rng: np.random.Generator, localiser: Localiser, size: int, pixel_mm: float,
                 style: str = "train") -> SliceBatch:
    """The slices of one generated scene of ``head`` that the service poses when the stack comes
    without a mask (the resampled pose mask covers at least :data:`MIN_MASK_FRACTION` of the input),
    as network inputs ``[n, size, size]`` with their true poses, network frame -> atlas mm (none
    where the localiser finds no brain); no thickness is recorded (the scenes' slice profiles are
    drawn inside the generator)."""
    scene = synth_scene(head, rng, style, rigid=True)
    prepared = prepare_stacks([StackUpload("scene.nii.gz", scene.volume)], model_grid(size, pixel_mm), False,
                              workers=1, localiser=localiser)[0]
    poses = prepared.in_network_frame(scene.atlas_from_voxel)
    keep = np.asarray(prepared.prepared.mask_fraction) >= MIN_MASK_FRACTION
    return SliceBatch(prepared.prepared.inputs[keep], poses[keep], ["scene"] * int(keep.sum()))


class LazyHeads:
    """The training brains as :class:`HeadModel` s, each made when first drawn (1-2 s a brain: a
    worker that starts with all of them would wait half a minute before its first batch)."""

    def __init__(self, volumes: list) -> None:  # noqa: ANN001 - model_export.atlas.AtlasVolume
        self.volumes, self.made = volumes, {}

    def __len__(self) -> int:
        return len(self.volumes)

    def __getitem__(self, i: int) -> HeadModel:
        if i not in self.made:
            v = self.volumes[i]
            self.made[i] = HeadModel.from_arrays(v.image, v.mask, v.affine)
        return self.made[i]


class ScenePool:
    """A training worker's scenes: each batch draws slices from all of them, and scenes are replaced
    at the rate that draws each slice about ``reuse`` times in all.

    Args:
        heads: the training brains (a list, or :class:`LazyHeads`).
        localiser: the localiser the service runs (one thread: a worker among many).
        size: the network's input, pixels a side.
        pixel_mm: the network's input pixel size.
        rng: the worker's generator.
        scenes: how many scenes the pool holds.
        reuse: how many times, on average, each slice is drawn before its scene is replaced.
    """

    def __init__(self, heads: list[HeadModel] | LazyHeads, localiser: Localiser, size: int, pixel_mm: float,
                 rng: np.random.Generator, scenes: int = 3, reuse: float = 8.0) -> None:
        self.heads, self.localiser, self.size, self.pixel_mm, self.rng = heads, localiser, size, pixel_mm, rng
        self.reuse = reuse
        self.pool = [self.fresh() for _ in range(scenes)]
        self.owed = 0.0

    def fresh(self) -> SliceBatch:
        """A new scene's slices (scenes where the localiser found nothing are drawn again)."""
        while True:
            batch = scene_slices(self.heads[int(self.rng.integers(len(self.heads)))], self.rng, self.localiser,
                                 self.size, self.pixel_mm)
            if len(batch.inputs):
                return batch

    def draw(self, n: int) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
        """``n`` slices drawn from the pool's scenes (inputs ``[n, L, L]``, poses ``[n, 4, 4]``); then
        the scenes the draws have used up are replaced."""
        inputs = np.concatenate([b.inputs for b in self.pool])
        poses = np.concatenate([b.poses for b in self.pool])
        pick = self.rng.integers(len(inputs), size=n)
        self.owed += n / (self.reuse * len(inputs) / len(self.pool))
        while self.owed >= 1.0:
            self.pool[int(self.rng.integers(len(self.pool)))] = self.fresh()
            self.owed -= 1.0
        return inputs[pick], poses[pick]
