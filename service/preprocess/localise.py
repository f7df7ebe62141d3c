"""Brain localisation for stacks sent without a mask: a learned network, then the stack's geometry.

1. **The network** (``<localisers_dir>/<name>/model.onnx``, run in onnxruntime): a 2.5D U-Net that
   sees every slice between its two neighbours on a grid of the model's ``grid_mm`` pixels
   (:func:`~service.preprocess.localiser_inputs.localiser_inputs`) and gives each pixel's
   probability of lying inside the fetal skull. It is trained on synthetic whole-uterus stacks only
   (atlas brains in generated surroundings; ``model_export.localiser``), so no scanner's contrast,
   pixel size or field of view is special to it. Each slice is seen laid out as a picture by the
   scanner's axes (:func:`~service.geometry.frames.in_plane_layout`), so a file that stores its
   rows or columns reversed or its in-plane axes swapped gets the same mask voxel for voxel (a
   network answers a picture and its turned copy a little differently; the measurements:
   docs/reports/localiser-experiments.md). Each slice is also
   seen mirrored along the picture's columns (the grid's ``W``), and the two answers' logits
   averaged: what the network decides by a narrow margin at the brain's edge (a face, a neck as
   wide as the head) is decided alike for every sampling a scanner makes of it. A network
   distilled from that average (``model_export.localiser.distil``; metadata ``mirrored_pass:
   learnt``) gives it in one pass. The network and the geometry see a stack's slices in one order
   whichever way its file stores them (:func:`reversed_slices`): a file that stores them last to
   first gets the same mask.
2. **The geometry** settles the answer (:mod:`service.preprocess.brain_shape`), on the network's
   grid: one 3D connected brain of a plausible volume for 20-40 weeks, without what hangs on to it
   through a waist or what a slice adds beyond its neighbours, its in-plane holes filled; then the
   probabilities inside that brain are brought back to the stack's own grid and cut at 0.4
   (:data:`~service.preprocess.brain_shape.MASK_THRESHOLD`).
3. **The confidence** (0..1) multiplies how sure the network is inside the brain, the share of all
   brain-like probability the chosen brain holds, and the plausibility of its volume. A stack with
   no brain (noise, another body part) gets a low confidence; below :data:`MIN_CONFIDENCE` its mask
   is empty and its slices are ``empty``.
4. **The pose network's mask** (:meth:`~service.preprocess.localisation.Localisation.pose_mask`): the localiser's mask is the skull's
   inside, as manual masks are drawn; the pose network learnt the atlas's tighter brain masks, so its
   slices are cut with the mask less its outer
   :data:`~service.preprocess.localisation.POSE_MASK_INSET_MM` (the localiser's mask as cut at
   :data:`~service.preprocess.brain_shape.THRESHOLD`, :attr:`~service.preprocess.localisation.Localisation.pose_region`).

Example (a localiser is an ONNX file; see :class:`Localiser`):
    >>> loc = Localiser.load(DEFAULT_LOCALISERS_DIR / "default" / "model.onnx")   # doctest: +SKIP
    >>> found = loc.localise(volume)                                               # doctest: +SKIP
    >>> found.method, found.brain_volume_ml, found.confidence                      # doctest: +SKIP
    ('network', 312.4, 0.93)
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort
from numpy.typing import NDArray
from scipy import ndimage

from service.core.cancellation import checkpoint
from service.core.errors import NotFound
from service.core.checksum import file_sha256
from service.core.onnx import load_models, session_options, session_threads
from service.core.settings import DEFAULT_LOCALISERS_DIR
from service.core.threads import side_by_side
from service.io.volume import Volume
from service.preprocess.brain_shape import THRESHOLD, brain_from_probabilities
from service.preprocess.slice_trims import margin_disk
from service.preprocess.localisation import Localisation
from service.preprocess.localiser_inputs import LocaliserGrid, localiser_inputs, target_maps
from service.preprocess.one_fetus import one_fetus
from service.preprocess.stack import blank_slices, mask_box, stack_axis

log = logging.getLogger(__name__)

MIN_SLICE_AREA_MM2 = 100.0
"""A slice's brain region smaller than this is not taken for a brain (:meth:`Localiser.localise_slice`)."""
MIN_CONFIDENCE = 0.15
"""Below this confidence no brain is reported: the mask is empty and the stack's slices ``empty``."""
BATCH_SLICES = 8
"""Slices per onnxruntime call of the localiser: on two cores a handful of 144 x 144 slices a call runs
faster per slice than a whole stack at once (the activations stay in cache)."""
MAX_STACK_MAPS = 32
"""A streamed slice's brain is settled among at most this many received slices of its stack, the nearest
(:meth:`Localiser.slice_in_stack`): the geometry's cost stays that of a stack of this size."""
SMALL_BRAIN_ML = 100.0
"""A brain found smaller than this (a fetus of under about 23 weeks, or part of a brain) is looked at
again on a finer grid (:meth:`Localiser.settle_closer`)."""
TYPICAL_BRAIN_ML = 250.0
"""... on which it appears at this volume, about the median of the heads the network learnt."""
MIN_GRID_SCALE = 0.6
"""The finer grid's pixels are at least this share of the model's."""
CUT_END_SHARE = 0.5
"""A stack's end slice cuts through a brain where it holds over this share of the brain's largest
slice (:func:`cut_by_stack_ends`): a brain's caps are smaller."""


@dataclass
class Localiser:
    """A localiser model file and its onnxruntime session (the metadata give its grid and version)."""

    path: Path
    session: ort.InferenceSession
    grid_mm: float
    version: str
    sha256: str
    mirrored: bool = True
    """Average each slice's logits with those of its mirror image (one more network pass a slice). A
    network that learnt that average (metadata ``mirrored_pass`` ``"learnt"``) runs once."""
    side_by_side: bool = False
    """Run the network's batches two at a time (:func:`~service.core.threads.side_by_side`), the
    session on half the cores: the U-Net's few channels gain little from a second intra-op thread."""
    licences: str = ""
    """The licences of its training data (metadata ``licences``; empty where the file names none)."""

    @classmethod
    def load(cls, path: Path, threads: int = 0) -> "Localiser":
        """Open ``path`` with onnxruntime and read its metadata; ``threads`` 0: all cores, two calls at
        a time (:func:`~service.core.onnx.session_threads`)."""
        path = Path(path)
        per_call, side = session_threads(threads)
        sess = ort.InferenceSession(str(path), session_options(per_call), providers=["CPUExecutionProvider"])
        meta = sess.get_modelmeta().custom_metadata_map
        return cls(path, sess, float(meta["grid_mm"]), meta.get("version", "unknown"), file_sha256(path),
                   mirrored=meta.get("mirrored_pass", "run") != "learnt", side_by_side=side,
                   licences=meta.get("licences", ""))

    def provenance(self) -> dict:
        """What made a mask: ``{"name", "version", "sha256"}`` (the name is the model's folder)."""
        return {"name": self.path.parent.name, "version": self.version, "sha256": self.sha256}

    def probabilities(self, volume: Volume) -> tuple[NDArray[np.float32], LocaliserGrid]:
        """Per-slice brain probabilities on the network grid ``[n, Hp, Wp]`` and that grid."""
        return self.probabilities_of([volume])[0]

    def probabilities_of(self, volumes: list[Volume], grids_mm: list[float] | None = None,
                         ) -> list[tuple[NDArray[np.float32], LocaliserGrid]]:
        """:meth:`probabilities` of several stacks, their slices sharing onnxruntime calls: the slices of
        all stacks whose network grids have one size go through the network together, in batches of
        :data:`BATCH_SLICES` (one request's stacks cost what their slices do, not a call each).
        ``grids_mm``: each stack's grid pixel size (default the model's)."""
        inputs = [localiser_inputs(v, g) for v, g in zip(volumes, grids_mm or [self.grid_mm] * len(volumes))]
        turned = [reversed_slices(v) for v in volumes]                 # seen last to first: slices and neighbours
        inputs = [(np.ascontiguousarray(x[::-1, ::-1]) if t else x, grid) for (x, grid), t in zip(inputs, turned)]
        feed = self.session.get_inputs()[0]
        out: list[NDArray | None] = [None] * len(volumes)
        for size in dict.fromkeys(x.shape[2:] for x, _ in inputs):
            which = [i for i, (x, _) in enumerate(inputs) if x.shape[2:] == size]
            x = np.concatenate([inputs[i][0] for i in which])
            if feed.shape[1] == 1:                              # a 2D localiser: the slice alone
                x = np.ascontiguousarray(x[:, 1:2])
            logits = self._logits(feed.name, x) if len(x) else np.zeros((0, *size), np.float32)
            ends = np.cumsum([0] + [len(inputs[i][0]) for i in which])
            for i, a, b in zip(which, ends[:-1], ends[1:]):
                out[i] = 1.0 / (1.0 + np.exp(-(logits[a:b][::-1] if turned[i] else logits[a:b])))
        return [(prob, grid) for prob, (_, grid) in zip(out, inputs)]

    def _logits(self, name: str, x: NDArray[np.float32]) -> NDArray[np.float32]:
        """The network's logits ``[n, H, W]`` for inputs ``[n, c, H, W]``, in batches of
        :data:`BATCH_SLICES` (:attr:`side_by_side`: two at a time); with :attr:`mirrored`, averaged
        with those of the inputs mirrored along ``W`` (mirrored back)."""
        seen = [x, np.ascontiguousarray(x[..., ::-1])] if self.mirrored else [x]
        edges = batch_edges(len(x), len(seen), self.side_by_side)
        batches = [(view, a, b) for view in seen for a, b in zip(edges[:-1], edges[1:])]
        run = lambda batch: self.session.run(None, {name: batch[0][batch[1]:batch[2]]})[0][:, 0]  # noqa: E731
        out = side_by_side(run, batches) if self.side_by_side else [run(batch) for batch in batches]
        logits = np.concatenate(out[:len(out) // len(seen)])
        if self.mirrored:
            logits = 0.5 * (logits + np.concatenate(out[len(out) // 2:])[..., ::-1])
        return logits

    def localise(self, volume: Volume, region: NDArray[np.bool_] | None = None) -> Localisation:
        """The brain mask of ``volume`` on its own grid, its volume and the confidence (``region``: see
        :meth:`settle_closer`)."""
        return self.localise_many([volume], regions=[region])[0]

    def localise_many(self, volumes: list[Volume], fixed: list[NDArray] | None = None,
                      regions: list[NDArray[np.bool_] | None] | None = None) -> list[Localisation]:
        """:meth:`localise` for each of ``volumes`` (one request's stacks: every one on the same
        fetus's brain, :func:`~service.preprocess.one_fetus.one_fetus`; ``fixed``: the centres of the
        request's uploaded masks, scanner mm; ``regions``: each stack's region of interest or None),
        the network run on their slices together (:meth:`probabilities_of`)."""
        answers = []
        for volume, (prob, grid), region in zip(volumes, self.probabilities_of(volumes), regions or [None] * len(volumes)):
            checkpoint()                          # the request's client may have left meanwhile
            answers.append(self.settle_closer(volume, prob, grid, region))
        return one_fetus(self, volumes, [found for _, found in answers], [a for a, _ in answers], fixed)

    def settle_closer(self, volume: Volume, prob: NDArray[np.float32], grid: LocaliserGrid,
                      region: NDArray[np.bool_] | None = None,
                      ) -> tuple[Localisation, tuple[NDArray[np.float32], LocaliserGrid]]:
        """:meth:`settle`, and where the brain is smaller than :data:`SMALL_BRAIN_ML`, the stack seen
        again on a grid of finer pixels, on which it appears at :data:`TYPICAL_BRAIN_ML` (the pixels
        at most :data:`MIN_GRID_SCALE` times finer), that answer kept where it finds a brain; with the
        probabilities the answer rests on. A brain that the stack's first or last slice cuts through
        is left as it is: it is part of a larger one (a stack that covers half the brain). With a
        ``region`` of interest (the stack's voxels the user drew around the head) the brain is the
        one that reaches into it (another head or a head-like structure outside it is passed over).

        The network is surest of heads of its training heads' usual size. A young fetus's head (under
        about 23 weeks) in a real uterus is not: at the model's grid the amniotic sac, head-sized at
        that age, looks like a head, and the network takes the sac in, or structures beside the
        head. On the finer grid the head is the size the network knows and the sac larger than any
        head (docs/reports/localiser-experiments.md, "A younger fetus")."""
        inside = (lambda g: None) if region is None else (lambda g: target_maps(region, volume, g) > 0.5)  # noqa: E731
        found = self.settle(volume, prob, grid, inside(grid))
        if not 0 < found.brain_volume_ml < SMALL_BRAIN_ML or cut_by_stack_ends(found.mask, volume):
            return found, (prob, grid)
        scale = float(np.clip((found.brain_volume_ml / TYPICAL_BRAIN_ML) ** (1 / 3), MIN_GRID_SCALE, 1.0))
        (finer, finer_grid), = self.probabilities_of([volume], [self.grid_mm * scale])
        there = self.settle(volume, finer, finer_grid, inside(finer_grid))
        return (there, (finer, finer_grid)) if there.mask.any() else (found, (prob, grid))

    def settle(self, volume: Volume, prob: NDArray[np.float32], grid: LocaliserGrid,
               prefer: NDArray[np.bool_] | None = None) -> Localisation:
        """The stack's geometry on its network probabilities (:meth:`probabilities`): one brain
        (:func:`brain_from_probabilities`; ``prefer``: the grid's pixels it must reach), back on the
        stack's grid."""
        axis = stack_axis(volume)
        voxel_ml = grid.grid_mm ** 2 * float(volume.spacing[axis]) / 1000.0
        seen = (lambda a: None if a is None else a[::-1]) if reversed_slices(volume) else (lambda a: a)
        brain, confidence = brain_from_probabilities(seen(prob), voxel_ml, grid.grid_mm, seen(blank_slices(volume)),
                                                     seen(prefer))
        brain = seen(brain)
        if not brain.any() or confidence < MIN_CONFIDENCE:
            return Localisation.of(np.zeros(volume.array.shape, bool), volume.spacing, "network", confidence)
        box = mask_box(brain, [0, 1, 1])                     # the brain and the ring of pixels around it
        near = ndimage.binary_dilation(brain[box], structure=np.ones((1, 3, 3), bool))
        kept = np.zeros_like(prob)
        kept[box] = np.where(near, np.maximum(prob[box], brain[box].astype(np.float32)), 0.0)
        return Localisation.found(grid.to_stack(kept), volume.spacing, confidence)

    def localise_slice(self, volume: Volume, which: int) -> Localisation:
        """The brain in slice ``which`` of ``volume`` (a few neighbouring slices of a stack that is still
        being acquired): :meth:`slice_in_stack` without the stack's other slices."""
        return self.slice_in_stack(volume, which)[0]

    def slice_in_stack(self, volume: Volume, which: int, others: Mapping[int, NDArray] | None = None,
                       index: int = 0, slice_mm: float | None = None,
                       ) -> tuple[Localisation, NDArray[np.float16] | None]:
        """The brain in slice ``which`` of ``volume`` (a few neighbouring slices of a stack that is still
        being acquired), and that slice's probability map on the network grid, which later calls take
        among ``others``.

        In the slice's probabilities, the 2D regions above :data:`~service.preprocess.brain_shape.THRESHOLD`
        are candidates; alone, the one with most probability is the brain. At the face end of a
        coronal stack that is the face, larger than the frontal lobes beside it, which is why
        ``others`` (the maps of the stack's slices received before it, by their index in the stack;
        ``index`` is this slice's; ``slice_mm`` the stack's step between slices, default the
        window's) settle it where they can: the geometry that settles a whole stack
        (:func:`brain_from_probabilities`) finds the brain in the received maps (the
        :data:`MAX_STACK_MAPS` nearest this slice), stacked in index order, and its region in this
        slice is the slice's brain (unless a sliver, under :data:`MIN_SLICE_AREA_MM2`: then the
        slice tells better). Where it misses this slice but holds one of the two on either
        side (past the brain's end, or a slice it trimmed), the candidate that reaches within
        :data:`~service.preprocess.slice_trims.OUTLIER_MARGIN_MM` of that slice's region is.
        Otherwise (no brain of two slices or more and :data:`MIN_CONFIDENCE` in the received maps,
        no candidate near it, or none of the maps on this slice's grid) the slice is judged alone:
        a stack whose face end arrives first has a face for its brain until the brain's own slices
        outweigh it. The chosen region's holes are filled. Its confidence multiplies how sure the
        network is inside it and the share of the slice's candidate probability it holds; below
        :data:`MIN_CONFIDENCE`, or under :data:`MIN_SLICE_AREA_MM2`, the slice has no brain. The
        returned mask covers ``volume``, brain only in slice ``which``. A slice that holds no image
        (:func:`~service.preprocess.stack.blank_slices`) has no brain and no map: the later slices'
        geometry joins the brain across it, as a whole stack's does."""
        empty = Localisation.of(np.zeros(volume.array.shape, bool), volume.spacing, "network", 0.0)
        if blank_slices(volume)[which]:
            return empty, None
        prob, grid = self.probabilities(volume)
        p = prob[which]
        own = p.astype(np.float16)
        labels, n = ndimage.label(p >= THRESHOLD)
        if n == 0:
            return empty, own
        mass = ndimage.sum_labels(p, labels, np.arange(1, n + 1))
        best = labels == int(np.argmax(mass)) + 1
        step = float(volume.spacing[stack_axis(volume)]) if slice_mm is None else float(slice_mm)
        in_stack = self._in_stack_brain(p, labels, others, index, step) if others else None
        if in_stack is not None:
            best = in_stack
        confidence = float(p[best].mean() * p[best & (labels > 0)].sum() / mass.sum())
        if best.sum() * self.grid_mm ** 2 < MIN_SLICE_AREA_MM2 or confidence < MIN_CONFIDENCE:
            return Localisation.of(empty.mask, volume.spacing, "network", confidence), own
        maps = np.zeros_like(prob)
        maps[which] = np.where(ndimage.binary_dilation(best, iterations=1), np.maximum(p, ndimage.binary_fill_holes(best)), 0.0)
        return Localisation.found(grid.to_stack(maps), volume.spacing, confidence), own    # slice by slice: only `which`

    def _in_stack_brain(self, p: NDArray, labels: NDArray, others: Mapping[int, NDArray], index: int,
                        slice_mm: float) -> NDArray[np.bool_] | None:
        """Where the brain of the received maps ``others`` lies in slice ``index`` (its map ``p``, its
        candidate regions ``labels``; :meth:`slice_in_stack`): its region there as the geometry leaves
        it, or the candidate that reaches its region in a slice beside it; None where the maps do not
        tell."""
        near = sorted((k for k, m in others.items() if k != index and m is not None and m.shape == p.shape),
                      key=lambda k: abs(k - index))[:MAX_STACK_MAPS - 1]
        if not near:
            return None
        order = sorted([*near, index])
        at = order.index(index)
        stacked = np.stack([p if k == index else np.asarray(others[k], np.float32) for k in order])
        gap_mm = float(np.median(np.diff(order))) * slice_mm
        brain, confidence = brain_from_probabilities(stacked, self.grid_mm ** 2 * gap_mm / 1000.0, self.grid_mm)
        rows = np.flatnonzero(brain.reshape(len(order), -1).any(1))
        if confidence < MIN_CONFIDENCE or len(rows) < 2:
            return None
        if brain[at].sum() * self.grid_mm ** 2 >= MIN_SLICE_AREA_MM2:
            return brain[at]
        if brain[at].any():                       # a sliver of what the maps hold: this slice tells better
            return None
        beside = int(rows[np.argmin(np.abs(np.asarray(order)[rows] - index))])
        if abs(order[beside] - index) > 2:
            return None
        reach = ndimage.binary_dilation(brain[beside], structure=margin_disk(self.grid_mm))
        overlap = ndimage.sum_labels(reach, labels, np.arange(1, int(labels.max()) + 1))
        return labels == int(np.argmax(overlap)) + 1 if overlap.max() > 0 else None


def batch_edges(slices: int, views: int = 1, paired: bool = False) -> list[int]:
    """Where a stack's ``slices`` are cut into the onnxruntime calls of one view: about
    :data:`BATCH_SLICES` a call, in calls of equal size; ``paired`` (two calls at a time, one per
    core, :func:`~service.core.threads.side_by_side`), in an even number of calls over the ``views``,
    so that neither core waits for the other's last call.

    Example (22 slices: one view, paired; two views; one view, one call at a time):
        >>> batch_edges(22, 1, True), batch_edges(22, 2, True), batch_edges(22)
        ([0, 6, 11, 16, 22], [0, 7, 15, 22], [0, 7, 15, 22])
    """
    calls = max(1, -(-slices // BATCH_SLICES))
    if paired and calls * views % 2 and calls < slices:
        calls += 1
    return [int(e) for e in np.linspace(0, slices, calls + 1).round()] if slices else [0]


def reversed_slices(volume: Volume) -> bool:
    """Whether the localiser sees ``volume``'s slices last to first: where its slice axis points
    against the scanner axis it runs most along (that component of its voxel axis negative). The
    same acquisition stored the other way round has the opposite answer, so the network, which sees
    each slice between its two neighbours, and a whole stack's geometry see both files' slices in
    one order (a streamed slice's geometry takes the received slices by their index).

    Example (only the slice axis's direction matters):
        >>> a = Volume(np.zeros((4, 4, 3), np.float32), np.diag([1.0, 1.0, 3.0, 1.0]))
        >>> b = Volume(a.array[:, :, ::-1], a.affine @ np.diag([1.0, 1.0, -1.0, 1.0]))
        >>> reversed_slices(a), reversed_slices(b)
        (False, True)
    """
    column = np.asarray(volume.affine, np.float64)[:3, stack_axis(volume)]
    return bool(column[int(np.argmax(np.abs(column)))] < 0)


def cut_by_stack_ends(mask: NDArray, volume: Volume) -> bool:
    """Whether the first or the last slice of ``volume`` cuts through the body of ``mask``'s brain:
    its brain there is over :data:`CUT_END_SHARE` of the brain's largest slice (a cap is smaller).

    Example (a brain of 3 slices of 4, 4 and 1 pixels: whole; without its first slice, cut):
        >>> m = np.zeros((4, 4, 5), bool); m[1:3, 1:3, 1:3] = True; m[1, 1, 3] = True
        >>> v = Volume(np.zeros((4, 4, 5), np.float32), np.diag([1.0, 1.0, 3.0, 1.0]))
        >>> cut_by_stack_ends(m, v), cut_by_stack_ends(m[..., 2:], v.region((slice(0, 4), slice(0, 4), slice(2, 5))))
        (False, True)
    """
    along = np.moveaxis(np.asarray(mask, bool), stack_axis(volume), 0)
    area = along.reshape(len(along), -1).sum(1)
    return bool(max(area[0], area[-1]) > CUT_END_SHARE * area.max())


@functools.cache
def default_localiser() -> Localiser:
    """The shipped default localiser, loaded once per process (for callers without a server's set)."""
    path = DEFAULT_LOCALISERS_DIR / "default" / "model.onnx"
    if not path.exists():
        raise NotFound("model: no localiser is installed; upload a brain mask for every stack")
    return Localiser.load(path)


class Localisers:
    """Name -> :class:`Localiser`: every ``<folder>/<name>/model.onnx``, loaded once."""

    def __init__(self, localisers: dict[str, Localiser], default_name: str = "default") -> None:
        self.localisers = localisers
        self.default_name = default_name

    @classmethod
    def from_directory(cls, folder: Path, threads: int = 0, names: tuple[str, ...] | None = None) -> "Localisers":
        """Every localiser of ``folder`` (``names``: those alone; :func:`~service.core.onnx.load_models`:
        :class:`~service.core.errors.UnusableModelFile` names a file that does not load)."""
        found = load_models(folder, "SVRNET_LOCALISERS_DIR", lambda path: Localiser.load(path, threads), names)
        for name in found:
            log.info("localiser loaded", extra={"model": name})
        return cls(found)

    def default(self) -> Localiser | None:
        """The default localiser, or None where none is installed under its name (a stream then takes
        slices with their masks only)."""
        return self.localisers.get(self.default_name)

    def describe(self) -> list[dict]:
        """The ``GET /v1/localisers`` body: each localiser's name, version, checksum, grid, licences,
        whether it is the default and whether its folder holds its card."""
        return [{"name": name, "version": loc.version, "sha256": loc.sha256, "default": name == self.default_name,
                 "grid_mm": loc.grid_mm, "licences": loc.licences, "card": (loc.path.parent / "card.md").is_file()}
                for name, loc in sorted(self.localisers.items())]

    def get(self, name: str = "default") -> Localiser:
        """The localiser ``name`` (``default``: the default one); :class:`NotFound` names the field."""
        resolved = self.default_name if name == "default" else name
        if resolved not in self.localisers:
            known = ", ".join(sorted(self.localisers)) or "none loaded"
            raise NotFound(f"model: unknown localiser {name!r} (available: {known})")
        return self.localisers[resolved]
