"""Brain localisation for stacks sent without a mask: a learned network, then the stack's geometry.

1. **The network** (``<localisers_dir>/<name>/model.onnx``, run in onnxruntime): a 2.5D U-Net that
   sees every slice between its two neighbours on a grid of the model's ``grid_mm`` pixels
   (:func:`~service.preprocess.localiser_inputs.localiser_inputs`) and gives each pixel's
   probability of lying inside the fetal skull. It is trained on synthetic whole-uterus stacks only
   (atlas brains in generated surroundings; ``model_export.localiser``), so no scanner's contrast,
   pixel size or field of view is special to it.
2. **The geometry** settles the answer (:func:`brain_from_probabilities`), on the network's grid:
   one 3D connected brain (the component with most probability, weighed by how plausible its
   volume is for 20-40 weeks), its in-plane holes filled; then the probabilities inside that brain are
   brought back to the stack's own grid and cut at 0.5.
3. **The confidence** (0..1) multiplies how sure the network is inside the brain, the share of all
   brain-like probability the chosen brain holds, and the plausibility of its volume. A stack with
   no brain (noise, another body part) gets a low confidence; below :data:`MIN_CONFIDENCE` its mask
   is empty and its slices are ``empty``.
4. **The pose network's mask** (:meth:`Localisation.pose_mask`): the localiser's mask is the skull's
   inside, as manual masks are drawn; the pose network learnt the atlas's tighter brain masks, so its
   slices are cut with the mask less its outer :data:`POSE_MASK_INSET_MM`.

Example (a localiser is an ONNX file; see :class:`Localiser`):
    >>> loc = Localiser.load(DEFAULT_LOCALISERS_DIR / "default" / "model.onnx")   # doctest: +SKIP
    >>> found = loc.localise(volume)                                               # doctest: +SKIP
    >>> found.method, found.brain_volume_ml, found.confidence                      # doctest: +SKIP
    ('network', 312.4, 0.93)
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort
from numpy.typing import NDArray
from scipy import ndimage

from service.core.errors import NotFound
from service.core.onnx import file_sha256, session_options
from service.core.settings import DEFAULT_LOCALISERS_DIR
from service.io.volume import Volume
from service.preprocess.localiser_inputs import LocaliserGrid, localiser_inputs
from service.preprocess.stack import mask_box, slice_axis_of

log = logging.getLogger(__name__)

PLAUSIBLE_ML = (30.0, 700.0)
"""Intracranial volumes of 20-40 weeks' gestation (brain and extra-axial CSF), with a margin."""
MIN_BRAIN_ML = 5.0
THRESHOLD = 0.5
MIN_SLICE_AREA_MM2 = 100.0
"""A slice's brain region smaller than this is not taken for a brain (:meth:`Localiser.localise_slice`)."""
MIN_CONFIDENCE = 0.15
"""Below this confidence no brain is reported: the mask is empty and the stack's slices ``empty``."""
BATCH_SLICES = 8
"""Slices per onnxruntime call of the localiser: on two cores a handful of 144 x 144 slices a call runs
faster per slice than a whole stack at once (the activations stay in cache)."""
WAIST_SHARE = 0.15
"""A slice of the brain's component whose area is under this share of the component's largest slice
on each side of it is a waist: a thin bridge into a neighbouring structure (:func:`cut_at_waists`)."""
WAIST_OVERLAP = 0.5
"""A thin slice is a waist only where the slices on either side of it overlap by less than this share
of the smaller: a brain's poor slice lies between two slices of one brain, a bridge between two objects."""
TAIL_SHARE = 0.35
"""What lies beyond a waist is cut off when it holds less than this share of the component's
probability mass; a larger part on each side is the brain itself, split by a poor slice."""
POSE_MASK_INSET_MM = 2.0
"""How far inside the localiser's mask (the skull's inside) the pose network's mask lies: the pose
network learnt the atlas's brain masks, which leave out most of the extra-axial CSF around the brain
(about 1-3.5 mm thick), and a mask that holds it costs the poses accuracy."""


@dataclass(frozen=True)
class Localisation:
    """Where a stack's brain is and how it was found (the ``localisation`` object of a response)."""

    mask: NDArray[np.bool_]
    method: str                    # "mask" (uploaded) or "network"
    brain_volume_ml: float
    confidence: float
    slices_with_brain: int
    holds_csf: bool = False
    """The mask is the skull's inside (the brain and the extra-axial CSF around it): the localiser's
    always, an uploaded one when the request says so (``masks_hold_csf``)."""

    @classmethod
    def of(cls, mask: NDArray, spacing: NDArray, method: str, confidence: float,
           holds_csf: bool | None = None) -> "Localisation":
        """A mask on a stack's grid of voxel sizes ``spacing``, with its volume and slice count
        (``holds_csf`` default: a localiser's mask does, an uploaded one does not)."""
        m = np.asarray(mask) > 0
        axis = slice_axis_of(spacing)
        slices = int(np.count_nonzero(np.moveaxis(m, axis, 0).reshape(m.shape[axis], -1).any(1)))
        csf = method == "network" if holds_csf is None else bool(holds_csf)
        return cls(m, method, float(m.sum() * np.prod(spacing) / 1000.0), float(confidence), slices, csf)

    @property
    def pose_inset_mm(self) -> float:
        """How far inside the mask the pose network's mask lies (:meth:`pose_mask`)."""
        return POSE_MASK_INSET_MM if self.holds_csf else 0.0

    def pose_mask(self, spacing: NDArray, axis: int | None = None) -> NDArray[np.bool_]:
        """The mask the pose network's slices are cut with: a tight brain mask as it is; one that holds
        the CSF around the brain (the localiser's, or an upload the request says holds it) without its outer
        :data:`POSE_MASK_INSET_MM` in the plane of the slices along ``axis`` (default: the thick one),
        the brain as the atlas masks the pose network learnt from draw it."""
        if not self.holds_csf or not self.mask.any():
            return self.mask
        return inset_in_plane(self.mask, np.asarray(spacing, np.float64), POSE_MASK_INSET_MM, axis)

    def report(self) -> dict:
        """The ``localisation`` object of a ``/v1/predict`` stack."""
        return {"method": self.method, "brain_volume_ml": round(self.brain_volume_ml, 1),
                "confidence": round(self.confidence, 3), "pose_mask_inset_mm": self.pose_inset_mm}


def plausibility(volume_ml: float | NDArray) -> float | NDArray:
    """1 inside :data:`PLAUSIBLE_ML`, falling off linearly in log-volume to 0 at a factor of 3 outside
    (element-wise for an array).

    Example:
        >>> plausibility(300.0), plausibility(10.0), round(plausibility(2100.0), 2)
        (1.0, 0.0, 0.0)
    """
    lo, hi = PLAUSIBLE_ML
    v = np.maximum(np.asarray(volume_ml, np.float64), 1e-9)
    out = np.clip(1.0 - np.maximum(np.maximum(np.log(lo / v), np.log(v / hi)), 0.0) / np.log(3.0), 0.0, 1.0)
    return float(out) if out.ndim == 0 else out


_IN_PLANE = np.zeros((3, 3, 3), bool)
_IN_PLANE[1] = ndimage.generate_binary_structure(2, 1)


def fill_holes_in_plane(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Each slice ``mask[k]`` with its 2D holes filled, in one pass over the mask's bounding box: an
    in-plane structuring element on the box padded by an empty slice at each end (so the end slices'
    faces are not taken for the outside).

    Example (a ring in the middle slice is filled; the column through all three slices is no hole):
        >>> m = np.zeros((3, 7, 7), bool); m[1, 1:6, 1:6] = True; m[1, 3, 3] = False; m[:, 5, 5] = True
        >>> out = fill_holes_in_plane(m)
        >>> bool(out[1, 3, 3]), int(out.sum() - m.sum())
        (True, 1)
    """
    found = np.argwhere(mask)
    if len(found) == 0:
        return np.zeros(mask.shape, bool)
    lo, hi = found.min(0), found.max(0) + 1
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    padded = np.pad(mask[box], ((1, 1), (1, 1), (1, 1)))
    out = np.zeros(mask.shape, bool)
    out[box] = ndimage.binary_fill_holes(padded, structure=_IN_PLANE)[1:-1, 1:-1, 1:-1]
    return out


def cut_at_waists(component: NDArray[np.bool_], prob: NDArray[np.float32]) -> NDArray[np.bool_]:
    """A 3D component of per-slice maps ``[n, H, W]`` without what hangs on to it through a waist.

    A brain's area grows from one cap to its widest slice and shrinks to the other cap. A component
    whose area falls, at some slice, under :data:`WAIST_SHARE` of its largest slice on each side holds
    two objects joined by a thin bridge (the brain leaking into the fetal neck and body, or into the
    amniotic fluid, across one slice), where the slices on either side of it do not overlap
    (:data:`WAIST_OVERLAP`; a poor slice of a brain lies between two overlapping ones). The part
    with most probability mass between waists is the brain; everything beyond a waist on either
    side, the waist included, is cut off when it holds under :data:`TAIL_SHARE` of the mass (a poor
    slice through the middle of a brain leaves two large parts and cuts nothing). What stays is the
    largest-mass 3D component of the rest.

    Example (a brain of 6 slices, a 2-pixel bridge, then a 3-slice blob beside it: the blob is cut off):
        >>> c = np.zeros((10, 12, 12), bool); c[0:6, 1:7, 1:7] = True; c[6, 6, 6:8] = True; c[7:10, 6:11, 6:11] = True
        >>> out = cut_at_waists(c, np.where(c, 0.9, 0.0).astype(np.float32))
        >>> out.reshape(10, -1).sum(1).tolist()
        [36, 36, 36, 36, 36, 36, 0, 0, 0, 0]
    """
    area = component.reshape(len(component), -1).sum(1)
    mass = np.where(component, prob, 0.0).reshape(len(component), -1).sum(1)
    rows = np.nonzero(area)[0]
    if len(rows) < 3:
        return component
    lo, hi = rows[0], rows[-1]
    before = np.maximum.accumulate(area[lo:hi + 1])
    after = np.maximum.accumulate(area[lo:hi + 1][::-1])[::-1]
    inner = np.arange(lo + 1, hi)
    thin = inner[area[inner] < WAIST_SHARE * np.minimum(before[inner - lo - 1], after[inner - lo + 1])]
    across = np.array([(component[k - 1] & component[k + 1]).sum() for k in thin])
    waists = thin[across < WAIST_OVERLAP * np.maximum(np.minimum(area[thin - 1], area[thin + 1]), 1)]
    if not len(waists):
        return component
    edges = np.concatenate([[lo - 1], waists, [hi + 1]])
    parts = [(a + 1, b) for a, b in zip(edges[:-1], edges[1:]) if b > a + 1]        # slices between waists
    core = max(parts, key=lambda ab: mass[ab[0]:ab[1]].sum())
    keep_from = core[0] if mass[:core[0]].sum() < TAIL_SHARE * mass.sum() else 0
    keep_to = core[1] if mass[core[1]:].sum() < TAIL_SHARE * mass.sum() else len(component)
    if (keep_from, keep_to) == (0, len(component)):
        return component
    kept = np.zeros_like(component)
    kept[keep_from:keep_to] = component[keep_from:keep_to]
    labels, n = ndimage.label(kept, structure=np.ones((3, 3, 3), bool))
    if n <= 1:
        return kept
    return labels == int(np.argmax(ndimage.sum_labels(prob, labels, np.arange(1, n + 1)))) + 1


def inset_in_plane(mask: NDArray, spacing: NDArray, inset_mm: float, axis: int | None = None) -> NDArray[np.bool_]:
    """``mask`` without the pixels within ``inset_mm`` of its outside, in the plane of each slice along
    ``axis`` (default: the thick one), by exact Euclidean distances on the voxel sizes ``spacing``.

    Example (a 20 x 20 mm square of 1 mm pixels loses 2 mm on each side):
        >>> m = np.zeros((30, 30, 3), bool); m[5:25, 5:25] = True
        >>> out = inset_in_plane(m, np.array([1.0, 1.0, 3.0]), 2.0)
        >>> int(out[:, :, 1].sum()), bool(out[:, :, 0].sum() == out[:, :, 1].sum())
        (256, True)
    """
    mask = np.asarray(mask, bool)
    found = np.argwhere(mask)
    if len(found) == 0:
        return mask.copy()
    axis = slice_axis_of(spacing) if axis is None else axis
    lo, hi = np.maximum(found.min(0) - 1, 0), found.max(0) + 2
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    sampling = np.array(spacing, np.float64)
    sampling[axis] = 1e6                                  # the nearest outside is always in the slice's plane
    inside = np.pad(mask[box], 1)
    distance = ndimage.distance_transform_edt(inside, sampling=sampling)[1:-1, 1:-1, 1:-1]
    out = np.zeros_like(mask)
    out[box] = mask[box] & (distance > inset_mm)
    return out


def brain_from_probabilities(prob: NDArray[np.float32], voxel_ml: float) -> tuple[NDArray[np.bool_], float]:
    """The brain's 3D component in per-slice probability maps ``[n, H, W]`` (``voxel_ml`` the volume of
    one grid voxel) and the confidence in it.

    Example (two blobs: the larger, surer one wins; the small one is dropped):
        >>> p = np.zeros((6, 20, 20), np.float32); p[1:5, 2:10, 2:10] = 0.95; p[2:3, 15:18, 15:18] = 0.6
        >>> brain, conf = brain_from_probabilities(p, voxel_ml=1.0)
        >>> int(brain.sum()), bool(brain[2, 16, 16]), round(conf, 2)
        (256, False, 0.93)
    """
    out = np.zeros(prob.shape, bool)
    above = prob >= THRESHOLD
    box = mask_box(above, [0, 0, 0])                          # every component lies inside it
    if box is None:
        return out, 0.0
    p = prob[box]
    labels, n = ndimage.label(above[box], structure=np.ones((3, 3, 3), bool))
    mass = np.bincount(labels.ravel(), weights=p.ravel(), minlength=n + 1)[1:]
    volume_of = np.bincount(labels.ravel(), minlength=n + 1)[1:] * voxel_ml
    best = int(np.argmax(mass * plausibility(volume_of) + 1e-6 * mass)) + 1
    brain = fill_holes_in_plane(cut_at_waists(labels == best, p))
    volume_ml = float(brain.sum() * voxel_ml)
    if volume_ml < MIN_BRAIN_ML:
        return out, 0.0
    out[box] = brain
    return out, float(p[brain].mean()) * float(mass[best - 1] / mass.sum()) * plausibility(volume_ml)


@dataclass
class Localiser:
    """A localiser model file and its onnxruntime session (the metadata give its grid and version)."""

    path: Path
    session: ort.InferenceSession
    grid_mm: float
    version: str
    sha256: str

    @classmethod
    def load(cls, path: Path, threads: int = 0) -> "Localiser":
        """Open ``path`` with onnxruntime (``threads`` 0: all cores) and read its metadata."""
        path = Path(path)
        sess = ort.InferenceSession(str(path), session_options(threads), providers=["CPUExecutionProvider"])
        meta = sess.get_modelmeta().custom_metadata_map
        return cls(path, sess, float(meta["grid_mm"]), meta.get("version", "unknown"), file_sha256(path))

    def probabilities(self, volume: Volume) -> tuple[NDArray[np.float32], LocaliserGrid]:
        """Per-slice brain probabilities on the network grid ``[n, Hp, Wp]`` and that grid."""
        return self.probabilities_of([volume])[0]

    def probabilities_of(self, volumes: list[Volume]) -> list[tuple[NDArray[np.float32], LocaliserGrid]]:
        """:meth:`probabilities` of several stacks, their slices sharing onnxruntime calls: the slices of
        all stacks whose network grids have one size go through the network together, in batches of
        :data:`BATCH_SLICES` (one request's stacks cost what their slices do, not a call each)."""
        inputs = [localiser_inputs(v, self.grid_mm) for v in volumes]
        feed = self.session.get_inputs()[0]
        out: list[NDArray | None] = [None] * len(volumes)
        for size in dict.fromkeys(x.shape[2:] for x, _ in inputs):
            which = [i for i, (x, _) in enumerate(inputs) if x.shape[2:] == size]
            x = np.concatenate([inputs[i][0] for i in which])
            if feed.shape[1] == 1:                              # a 2D localiser: the slice alone
                x = np.ascontiguousarray(x[:, 1:2])
            logits = np.concatenate([self.session.run(None, {feed.name: x[k:k + BATCH_SLICES]})[0][:, 0]
                                     for k in range(0, len(x), BATCH_SLICES)]) if len(x) else np.zeros((0, *size))
            ends = np.cumsum([0] + [len(inputs[i][0]) for i in which])
            for i, a, b in zip(which, ends[:-1], ends[1:]):
                out[i] = 1.0 / (1.0 + np.exp(-logits[a:b]))
        return [(prob, grid) for prob, (_, grid) in zip(out, inputs)]

    def localise(self, volume: Volume) -> Localisation:
        """The brain mask of ``volume`` on its own grid, its volume and the confidence."""
        return self.localise_many([volume])[0]

    def localise_many(self, volumes: list[Volume]) -> list[Localisation]:
        """:meth:`localise` for each of ``volumes``, the network run on their slices together
        (:meth:`probabilities_of`)."""
        return [self._settle(v, prob, grid) for v, (prob, grid) in zip(volumes, self.probabilities_of(volumes))]

    def _settle(self, volume: Volume, prob: NDArray[np.float32], grid: LocaliserGrid) -> Localisation:
        """The stack's geometry on its network probabilities: one brain (:func:`brain_from_probabilities`),
        back on the stack's grid."""
        axis = slice_axis_of(volume.spacing)
        voxel_ml = self.grid_mm ** 2 * float(volume.spacing[axis]) / 1000.0
        brain, confidence = brain_from_probabilities(prob, voxel_ml)
        if not brain.any() or confidence < MIN_CONFIDENCE:
            return Localisation.of(np.zeros(volume.array.shape, bool), volume.spacing, "network", confidence)
        box = mask_box(brain, [0, 1, 1])                     # the brain and the ring of pixels around it
        near = ndimage.binary_dilation(brain[box], structure=np.ones((1, 3, 3), bool))
        kept = np.zeros_like(prob)
        kept[box] = np.where(near, np.maximum(prob[box], brain[box].astype(np.float32)), 0.0)
        return Localisation.of(grid.to_stack(kept) >= THRESHOLD, volume.spacing, "network", confidence)

    def localise_slice(self, volume: Volume, which: int) -> Localisation:
        """The brain in slice ``which`` of ``volume`` (a few neighbouring slices of a stack that is still
        being acquired): in that slice's probabilities, the 2D region with most brain probability,
        its holes filled, back on the slice's grid. Its confidence multiplies how sure the network is
        inside it and the share of the slice's brain-like probability it holds; below
        :data:`MIN_CONFIDENCE`, or under :data:`MIN_SLICE_AREA_MM2`, the slice has no brain. The
        returned mask covers ``volume``, brain only in slice ``which``."""
        prob, grid = self.probabilities(volume)
        p = prob[which]
        labels, n = ndimage.label(p >= THRESHOLD)
        axis = slice_axis_of(volume.spacing)
        empty = Localisation.of(np.zeros(volume.array.shape, bool), volume.spacing, "network", 0.0)
        if n == 0:
            return empty
        mass = ndimage.sum_labels(p, labels, np.arange(1, n + 1))
        best = labels == int(np.argmax(mass)) + 1
        confidence = float(p[best].mean() * mass.max() / mass.sum())
        if best.sum() * self.grid_mm ** 2 < MIN_SLICE_AREA_MM2 or confidence < MIN_CONFIDENCE:
            return Localisation.of(empty.mask, volume.spacing, "network", confidence)
        maps = np.zeros_like(prob)
        maps[which] = np.where(ndimage.binary_dilation(best, iterations=1), np.maximum(p, ndimage.binary_fill_holes(best)), 0.0)
        mask = grid.to_stack(maps) >= THRESHOLD
        only = np.zeros(volume.array.shape, bool)
        keep = [slice(None)] * 3
        keep[axis] = which
        only[tuple(keep)] = mask[tuple(keep)]
        return Localisation.of(only, volume.spacing, "network", confidence)

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
    def from_directory(cls, folder: Path, threads: int = 0) -> "Localisers":
        found = {p.parent.name: Localiser.load(p, threads) for p in sorted(Path(folder).glob("*/model.onnx"))}
        for name in found:
            log.info("localiser loaded", extra={"model": name})
        return cls(found)

    def get(self, name: str = "default") -> Localiser:
        """The localiser ``name`` (``default``: the default one); :class:`NotFound` names the field."""
        resolved = self.default_name if name == "default" else name
        if resolved not in self.localisers:
            known = ", ".join(sorted(self.localisers)) or "none loaded"
            raise NotFound(f"model: unknown localiser {name!r} (available: {known})")
        return self.localisers[resolved]
