"""Synthetic whole-uterus stacks: an atlas brain in generated surroundings (domain randomisation).

A stack is generated in its own frame (``x`` along columns, ``y`` along rows, ``z`` the slice normal,
millimetres, the field of view centred on 0), at a random in-plane pixel size, field of view (mostly
250-400 mm, sometimes cropped to 130-250 mm), slice thickness and slice count, in the way SynthSeg and SynthStrip train on synthetic images:
every tissue's intensity, shape and texture is drawn at random, so that the network learns the
brain's shape and its setting, not one scanner's contrast.

* **Surroundings**, on a grid of twice the pixel size, made of analytic shapes distorted by smooth
  noise: the mother's body (an ellipsoid; air outside), a subcutaneous fat layer, maternal tissue
  split into random labels, a uterus with its wall and a placenta, amniotic fluid, the fetal body
  (spine, fluid-filled organs) and limbs. Some organs and maternal tissues carry *decoy* texture:
  the atlas brain's interior, folded and tiled, so that texture alone never says "brain" and the
  network must learn the head's shape and setting (skull, CSF rim, size).
* **The fetal head** at the stack's own resolution, with the slice profile (three sub-planes
  averaged): the atlas brain (its T2 intensities, remapped by a random gamma), then an extra-axial
  CSF layer, the skull and the scalp, all from the atlas mask's signed distance. Most heads
  (:data:`FACE_SHARE`) also have a face below the frontal lobes (two bright, fluid-filled eyes in
  textured soft tissue) and a neck leaving the skull base towards the trunk: on a T2 scan the eyes
  in textured tissue, right under the brain, look much like a piece of it. The head takes any
  orientation and moves from slice to slice (small drift plus occasional jumps).
* **Hard settings**: some heads sit at or beyond the uterine wall, low in the maternal pelvis
  (:data:`ENGAGED_SHARE`); some lie in tissue as bright and as textured as the brain, behind a thin CSF
  layer and skull (:data:`CAMOUFLAGE_SHARE`), so that neither a fluid rim nor a brain brighter than its
  surroundings is what the network learns to look for.
* **Acquisition**: a smooth multiplicative bias field and, for half the stacks, a surface coil's
  fall-off; slice-to-slice intensity changes; noise.

The brain mask the network learns is everything inside the skull (brain and extra-axial CSF), as
manual fetal brain masks are drawn.

Two *styles* share the head and differ in everything around it: ``"train"`` (maternal tissue from
the arg-max of smooth noise fields, Rician noise, T2-like intensity priors with 20 % fully random
draws) and ``"heldout"`` (maternal tissue from Voronoi cells, a squarer uterus, Gaussian noise, a
polynomial bias field, half the stacks with every intensity drawn uniformly), so that a validation set of the held-out style measures
generalisation rather than memory of the generator.

Example:
    >>> import numpy as np
    >>> from model_export.localiser.scenes import HeadModel, synth_stack
    >>> mask = np.zeros((40, 48, 44), np.float32); mask[8:32, 10:38, 8:36] = 1
    >>> head = HeadModel.from_arrays(mask * 1000.0, mask, np.diag([2.0, 2.0, 2.0, 1.0]))
    >>> vol, brain = synth_stack(head, np.random.default_rng(0))
    >>> vol.array.shape == brain.shape, brain.dtype, bool(brain.any())
    (True, dtype('bool'), True)
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.spatial.transform import Rotation

from model_export.atlas import signed_distance
from service.io.volume import Volume

STYLES = ("train", "heldout")
ENGAGED_SHARE = {"train": 0.3, "heldout": 0.25}
"""Share of stacks whose head sits at or beyond the uterine wall (late pregnancy, head in the maternal
pelvis): the scalp meets maternal tissue or the wall, with little or no amniotic fluid around it."""
CAMOUFLAGE_SHARE = {"train": 0.25, "heldout": 0.15}
"""Share of stacks whose head lies in tissue as bright and as textured as the brain, as a head deep in
the maternal pelvis does on a T2 scan: a thin CSF layer and the skull are all that tell where the brain
ends, so the network cannot rely on a fluid rim or on the brain outshining its surroundings."""
FACE_SHARE = {"train": 0.8, "heldout": 0.8}
"""Share of heads drawn with a face (eyes in soft tissue below the frontal lobes) and a neck towards the
trunk; the rest are the bare skull, scalp and a trunk in any direction."""
BRAIN_LIKE_FACE_SHARE = {"train": 0.0, "heldout": 0.5}
"""Share of faces whose soft tissue is as bright as the brain (the rest: as bright as the fetal body)."""
NECK_AXIS = np.array([0.0, -0.3, -1.0]) / np.hypot(0.3, 1.0)
"""The neck's direction in the head's atlas frame (RAS: down and a little back)."""


@dataclass
class HeadModel:
    """An atlas brain ready for sampling: normalised T2, signed distance to its mask (mm, < 0 inside)."""

    t2: NDArray[np.float32]
    sdf: NDArray[np.float32]
    voxel_from_mm: NDArray[np.float64]       # centred brain mm -> voxel index (4 x 4)
    radius_mm: float
    atlas_from_voxel: NDArray[np.float64] | None = None    # the atlas volume's voxel -> world (atlas mm)

    @cached_property
    def brain_t2(self) -> NDArray[np.float32]:
        """A seventh of the brain's voxel intensities (what a scene's mean brain intensity is taken from)."""
        return np.clip(self.t2[self.sdf <= 0][::7], 1e-3, None)

    @cached_property
    def half_extent_mm(self) -> NDArray[np.float64]:
        """``[3]`` half the brain's extent along the head model's axes, mm: its volume's voxel axes, which
        are the atlas's (x right, y anterior, z superior) for the shared atlases (diagonal affines)."""
        idx = np.argwhere(self.sdf <= 0)
        mm = (idx - self.voxel_from_mm[:3, 3]) / np.diag(self.voxel_from_mm)[:3]
        return (mm.max(0) - mm.min(0)) / 2.0

    @classmethod
    def from_arrays(cls, image: NDArray, mask: NDArray, affine: NDArray) -> "HeadModel":
        """From an atlas image, its brain mask and its voxel -> mm affine."""
        inside = np.asarray(mask) > 0.5
        spacing = np.sqrt((np.asarray(affine)[:3, :3] ** 2).sum(0))
        sdf = signed_distance(inside, spacing)
        t2 = np.where(inside, image, 0.0).astype(np.float32)
        t2 /= max(float(np.percentile(t2[inside], 99.0)), 1e-6)
        idx = np.argwhere(inside)
        centre = idx.mean(0)
        radius = float(np.sqrt((((idx - centre) * spacing) ** 2).sum(1)).max())
        mm_from_voxel = np.diag([*spacing, 1.0])
        mm_from_voxel[:3, 3] = -centre * spacing
        return cls(np.clip(t2, 0, 1.5), sdf, np.linalg.inv(mm_from_voxel), radius, np.asarray(affine, np.float64))


@dataclass
class Face:
    """A face and a neck in the head's own frame (atlas axes, mm from the brain's centre), drawn
    outside the skull: two fluid-filled eyes below the frontal lobes in textured soft tissue, and a
    neck leaving the skull base (a dark vertebral column at its back) along :data:`NECK_AXIS`."""

    eyes: NDArray[np.float64]          # [2, 3] centres
    eye_radius: float
    eye_level: float
    tissue_centre: NDArray[np.float64]
    tissue_axes: NDArray[np.float64]
    tissue_level: float
    neck_start: NDArray[np.float64]
    neck_radius: float
    neck_length: float
    spine_level: float
    waves: NDArray[np.float64]         # [w, 3] wave vectors of the soft tissue's texture (rad / mm)
    phases: NDArray[np.float64]
    amplitude: float
    cells: bool                        # the texture as patches (``heldout``) rather than waves

    @classmethod
    def draw(cls, rng: np.random.Generator, head: HeadModel, tissue: dict[str, float], brain_level: float,
             outside_mm: float, style: str) -> "Face":
        """A face for ``head``; ``outside_mm``: the skull's outer surface (signed distance from the brain)."""
        hx, hy, hz = head.half_extent_mm
        radius = rng.uniform(0.13, 0.18) * hy
        side = rng.uniform(0.32, 0.45) * hx
        centre = np.array([0.0, rng.uniform(0.55, 0.75) * hy, -rng.uniform(0.45, 0.7) * hz])
        away = np.array([0.0, 0.2, -1.0]) / np.hypot(0.2, 1.0)
        for _ in range(60):                                        # below the skull, not in the brain
            eyes = centre + np.array([[-side, 0.0, 0.0], [side, 0.0, 0.0]])
            vox = eyes @ head.voxel_from_mm[:3, :3].T + head.voxel_from_mm[:3, 3]
            if ndimage.map_coordinates(head.sdf, vox.T, order=1, mode="nearest").min() >= outside_mm + 0.6 * radius:
                break
            centre = centre + away
        brain_like = rng.random() >= 1.0 - BRAIN_LIKE_FACE_SHARE[style]      # the upper draws: seeds keep their faces
        level = brain_level * rng.uniform(0.6, 1.2) if brain_like else tissue["body"] * rng.uniform(0.8, 1.5)
        count = 6
        directions = rng.normal(size=(count, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        return cls(eyes, radius, tissue["fluid"] * rng.uniform(0.85, 1.05),
                   np.array([0.0, rng.uniform(0.5, 0.7) * hy, -rng.uniform(0.6, 0.8) * hz]),
                   np.array([rng.uniform(0.6, 0.8) * hx, rng.uniform(0.45, 0.6) * hy, rng.uniform(0.45, 0.6) * hz]),
                   level, np.array([0.0, -0.35 * hy, -0.55 * hz]), rng.uniform(0.45, 0.65) * hx,
                   rng.uniform(0.6, 1.0) * hz, tissue["skull"],
                   directions * (2 * np.pi / rng.uniform(4.0, 14.0, (count, 1))), rng.uniform(0, 2 * np.pi, count),
                   rng.uniform(0.1, 0.35), style == "heldout")

    @property
    def reach_mm(self) -> float:
        """How far from the brain's centre the face and neck reach."""
        ends = [np.linalg.norm(self.tissue_centre) + self.tissue_axes.max(),
                np.linalg.norm(self.neck_start + NECK_AXIS * self.neck_length) + self.neck_radius]
        return float(max(ends))

    def render(self, local: NDArray) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """Intensities at head-frame points ``local [..., 3]`` and where the face or neck is."""
        texture = np.sin(local @ self.waves.T + self.phases).mean(-1)
        if self.cells:
            texture = np.tanh(4.0 * texture)
        soft = self.tissue_level * (1.0 + self.amplitude * texture)
        along = (local - self.neck_start) @ NECK_AXIS
        across = local - self.neck_start - along[..., None] * NECK_AXIS
        neck = (along >= -self.neck_radius) & (along <= self.neck_length) \
            & (np.linalg.norm(across, axis=-1) <= self.neck_radius)
        back = across + np.array([0.0, 0.4 * self.neck_radius, 0.0])        # the column at the neck's back
        spine = neck & (np.linalg.norm(back - (back @ NECK_AXIS)[..., None] * NECK_AXIS, axis=-1) < 0.2 * self.neck_radius)
        tissue = (((local - self.tissue_centre) / self.tissue_axes) ** 2).sum(-1) <= 1.0
        eye = np.min(np.linalg.norm(local[..., None, :] - self.eyes, axis=-1), axis=-1) <= self.eye_radius
        values = np.where(eye, self.eye_level, np.where(spine, self.spine_level, soft))
        return values.astype(np.float32), eye | tissue | neck


def _random_rotation(rng: np.random.Generator) -> NDArray[np.float64]:
    return Rotation.random(random_state=int(rng.integers(2**31))).as_matrix()


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, ...], cells: tuple[int, ...]) -> NDArray[np.float32]:
    """Zero-mean, unit-scale smooth noise on ``shape``: Gaussian noise on ``cells`` points, upsampled."""
    small = rng.standard_normal(cells).astype(np.float32)
    out = ndimage.zoom(small, [s / c for s, c in zip(shape, cells)], order=1, mode="nearest", grid_mode=True)
    return out[tuple(slice(0, s) for s in shape)]


def _ellipsoid_radius(points: NDArray, centre: NDArray, axes: NDArray, rotation: NDArray) -> NDArray[np.float32]:
    """Normalised radius of ``points [..., 3]`` in an ellipsoid (1 on its surface)."""
    local = (points - centre) @ rotation / axes
    return np.sqrt((local ** 2).sum(-1)).astype(np.float32)


def _intensities(rng: np.random.Generator, random_contrast: bool) -> dict[str, float]:
    """Mean intensity of each tissue: T2-like (fluid bright, skull dark), or each drawn uniformly."""
    if random_contrast:
        names = ("fluid", "csf", "skull", "scalp", "body", "wall", "placenta", "fat", "air")
        out = {k: float(rng.uniform(0.0, 1.0)) for k in names}
        out["air"] *= 0.3
        return out
    fluid = rng.uniform(0.7, 1.0)
    return {"fluid": fluid, "csf": fluid * rng.uniform(0.85, 1.1), "skull": rng.uniform(0.0, 0.15),
            "scalp": rng.uniform(0.15, 0.5), "body": rng.uniform(0.15, 0.55), "wall": rng.uniform(0.15, 0.5),
            "placenta": rng.uniform(0.25, 0.6), "fat": rng.uniform(0.4, 1.6), "air": rng.uniform(0.0, 0.05)}


@dataclass
class StackGeometry:
    pixel_mm: float
    size: int
    thickness_mm: float
    gap_mm: float
    slices: int

    @classmethod
    def draw(cls, rng: np.random.Generator) -> "StackGeometry":
        pixel = rng.uniform(0.9, 1.6)
        fov = rng.uniform(250.0, 400.0) if rng.random() > 0.12 else rng.uniform(130.0, 250.0)   # some cropped
        thickness = rng.uniform(2.0, 4.5)
        gap = thickness * rng.uniform(0.85, 1.15)
        slices = int(np.clip(rng.uniform(60.0, 140.0) / gap, 12, 48))
        return cls(pixel, int(fov / pixel), thickness, gap, slices)

    def box(self, centre: NDArray, reach_mm: float) -> tuple[slice, slice]:
        """The in-plane pixel box within ``reach_mm`` of ``centre`` (mm, as :meth:`coordinates`)."""
        lo = np.clip(np.floor((centre[:2] - reach_mm) / self.pixel_mm + (self.size - 1) / 2.0), 0, self.size).astype(int)
        hi = np.clip(np.ceil((centre[:2] + reach_mm) / self.pixel_mm + (self.size - 1) / 2.0) + 1, 0, self.size).astype(int)
        return slice(lo[0], hi[0]), slice(lo[1], hi[1])

    def coordinates(self, step: int = 1) -> NDArray[np.float32]:
        """``[size/step, size/step, slices, 3]`` pixel centres (mm) on a grid ``step`` times coarser in-plane."""
        n = int(np.ceil(self.size / step))
        xy = ((np.arange(n) + 0.5) * step - 0.5 - (self.size - 1) / 2.0) * self.pixel_mm
        z = (np.arange(self.slices) - (self.slices - 1) / 2.0) * self.gap_mm
        return np.stack(np.meshgrid(xy, xy, z, indexing="ij"), -1).astype(np.float32)


def _maternal_labels(rng: np.random.Generator, shape: tuple[int, ...], style: str, count: int) -> NDArray[np.int8]:
    if style == "train":
        fields = np.stack([_smooth_noise(rng, shape, (rng.integers(4, 12),) * 2 + (rng.integers(2, 5),))
                           for _ in range(count)])
        return np.argmax(fields, 0).astype(np.int8)
    small = tuple(max(2, s // 4) for s in shape)
    seeds = rng.uniform(0, 1, (count * 6, 3)) * np.array(small)
    grid = np.stack(np.meshgrid(*[np.arange(s, dtype=np.float32) for s in small], indexing="ij"), -1)
    cells = (np.argmin(((grid[..., None, :] - seeds) ** 2).sum(-1), axis=-1) % count).astype(np.int8)
    out = ndimage.zoom(cells, [s / c for s, c in zip(shape, small)], order=0, grid_mode=True, mode="nearest")
    return out[tuple(slice(0, s) for s in shape)]


def _surroundings(rng: np.random.Generator, geo: StackGeometry, brain_centre: NDArray, head_radius: float,
                  tissue: dict[str, float], style: str, decoy: HeadModel | None = None,
                  neck: NDArray | None = None) -> NDArray[np.float32]:
    """The scene without the head, on the half-resolution grid ``[n, n, slices]``; ``neck``: the
    direction (stack frame) the fetal trunk lies in from the head, roughly (default any)."""
    pts = geo.coordinates(step=2)
    shape = pts.shape[:3]
    def wobble(amount: float) -> NDArray[np.float32]:
        return amount * _smooth_noise(rng, shape, (5, 5, 3))
    # the mother: an ellipsoid body, air outside, a fat layer under the skin, tissues inside
    body_r = _ellipsoid_radius(pts, rng.normal(0, 30, 3), rng.uniform([150, 110, 150], [230, 180, 260]),
                               _random_rotation(rng)) + wobble(0.03)
    fat_depth = rng.uniform(0.04, 0.15)
    n_labels = int(rng.integers(3, 7))
    labels = _maternal_labels(rng, shape, style, n_labels)
    means = rng.uniform(0.02, 0.9, n_labels) if style == "heldout" else \
        np.concatenate([[tissue["fat"]], rng.uniform(0.02, 0.7, n_labels - 1)])
    image = means[labels].astype(np.float32) * (1 + 0.25 * _smooth_noise(rng, shape, (24, 24, 6)))
    if rng.random() < 0.5:                                   # bowel gas and fluid-filled loops: small blobs
        blobs = _smooth_noise(rng, shape, (40, 40, 8))
        image = np.where(blobs > 1.6, rng.choice([0.02, tissue["fluid"]]), image)
    image = np.where(body_r > 1 - fat_depth, tissue["fat"], image)
    image = np.where(body_r > 1, tissue["air"], image)
    # the fetal body beside the head (its near end at the head), and a few limbs
    direction = rng.normal(size=3)
    if neck is not None:
        direction = neck + 0.3 * direction / np.linalg.norm(direction)
    direction /= np.linalg.norm(direction)
    length = rng.uniform(1.0, 2.0) * head_radius
    trunk_c = brain_centre + direction * (head_radius + rng.uniform(0.7, 1.0) * length)
    # the uterus around the fetus: wall, placenta on one side, amniotic fluid
    axes = rng.uniform(70, 150, 3)
    uterus_c = (brain_centre + trunk_c) / 2 + rng.normal(0, 0.15, 3) * axes
    rot = _random_rotation(rng)
    if rng.random() < ENGAGED_SHARE[style]:      # the head low in the pelvis or against the wall: no fluid rim
        along = np.linalg.norm(rot.T @ direction / axes)           # normalised uterine radius per mm along the body
        uterus_c = brain_centre + direction * rng.uniform(0.8, 1.3) / along
    uterus_r = _ellipsoid_radius(pts, uterus_c, axes, rot) + wobble(0.06)
    if style == "heldout":                                      # a squarer uterus
        local = np.abs((pts - uterus_c) @ rot / axes)
        uterus_r = ((local ** 4).sum(-1) ** 0.25).astype(np.float32) + wobble(0.04)
    wall = rng.uniform(4, 12) / axes.mean()
    image = np.where(uterus_r <= 1, tissue["wall"], image)
    side = rot[:, 0] * rng.choice([-1, 1])
    towards = ((pts - uterus_c) @ side) / (np.linalg.norm(pts - uterus_c, axis=-1) + 1e-3)
    placenta = (uterus_r <= 1) & (uterus_r > 1 - rng.uniform(0.15, 0.35)) & (towards > rng.uniform(0.3, 0.8))
    image = np.where(placenta, tissue["placenta"] * (1 + 0.15 * _smooth_noise(rng, shape, (20, 20, 5))), image)
    fluid = tissue["fluid"] * (1 + rng.uniform(0, 0.1) * _smooth_noise(rng, shape, (8, 8, 3)))
    image = np.where(uterus_r <= 1 - wall, fluid, image)
    trunk_rot = Rotation.align_vectors([direction], [[1.0, 0.0, 0.0]])[0].as_matrix()
    body = _ellipsoid_radius(pts, trunk_c, np.array([length, *rng.uniform(0.5, 0.9, 2) * head_radius]),
                             trunk_rot) + wobble(0.05) <= 1
    for _ in range(int(rng.integers(0, 5))):
        c = trunk_c + rng.normal(0, 1, 3) * length
        body |= _ellipsoid_radius(pts, c, rng.uniform(6, 25, 3), _random_rotation(rng)) <= 1
    body_texture = tissue["body"] * (1 + 0.3 * _smooth_noise(rng, shape, (30, 30, 8)))
    if decoy is not None and rng.random() < 0.6:               # organs as rich in texture as a brain
        body_texture = tissue["body"] * (0.4 + 1.2 * _decoy_texture(rng, decoy, pts, trunk_c))
    local = (pts - trunk_c) @ trunk_rot                           # the spine: a dark rod along the trunk
    spine = (np.hypot(local[..., 1] - rng.uniform(-0.5, 0.5) * head_radius, local[..., 2]) < rng.uniform(3, 7)) \
        & (np.abs(local[..., 0]) < length)
    body_texture = np.where(spine, tissue["skull"], body_texture)
    for _ in range(int(rng.integers(0, 4))):                       # stomach, bladder, heart: fluid-like blobs
        c = trunk_c + (rng.uniform(-0.6, 0.6, 3) * [length, 0.4 * head_radius, 0.4 * head_radius]) @ trunk_rot.T
        blob = _ellipsoid_radius(pts, c, rng.uniform(6, 18, 3), _random_rotation(rng)) <= 1
        body_texture = np.where(blob, tissue["fluid"] * rng.uniform(0.5, 1.0), body_texture)
    image = np.where(body & (uterus_r <= 1), body_texture, image)
    if decoy is not None and rng.random() < 0.4:               # a maternal tissue textured like a brain
        label = int(rng.integers(n_labels))
        texture = means[label] * (0.4 + 1.2 * _decoy_texture(rng, decoy, pts, pts.reshape(-1, 3).mean(0)))
        image = np.where((labels == label) & (body_r <= 1 - fat_depth) & (uterus_r > 1), texture, image)
    return image.astype(np.float32)


def _decoy_texture(rng: np.random.Generator, head: HeadModel, pts: NDArray, centre: NDArray) -> NDArray[np.float32]:
    """Brain-like texture without a brain's shape: the atlas interior, folded into a cube and tiled
    at a random scale and orientation (0..1)."""
    half = rng.uniform(12.0, 22.0)
    local = ((pts - centre) @ _random_rotation(rng)) * rng.uniform(0.6, 1.4)
    folded = np.abs(np.mod(local + half, 4 * half) - 2 * half) - half       # a mirror tiling of the cube
    vox = folded @ head.voxel_from_mm[:3, :3].T + head.voxel_from_mm[:3, 3]
    t2 = ndimage.map_coordinates(head.t2, np.moveaxis(vox, -1, 0), order=1, mode="nearest")
    return np.clip(t2, 0, 1.2).astype(np.float32) ** rng.uniform(0.7, 1.4)


def _camouflage(rng: np.random.Generator, geo: StackGeometry, background: NDArray[np.float32], centre: NDArray,
                head_radius: float, level: float, style: str, decoy: HeadModel) -> NDArray[np.float32]:
    """``background`` with the tissue around the head (a distorted ellipsoid 1.2-2x the head's
    radius) replaced by tissue of the brain's ``level`` times 0.6-1.4, textured: the atlas interior
    folded and tiled (``train``) or Voronoi-like cells of random intensities (``heldout``)."""
    reach = 2.0 * head_radius + 10.0
    box = geo.box(centre, reach)
    pts = geo.coordinates()[box]
    shape = pts.shape[:3]
    radius = _ellipsoid_radius(pts, centre, head_radius * rng.uniform(1.2, 2.0, 3), _random_rotation(rng)) \
        + 0.15 * _smooth_noise(rng, shape, (6, 6, 3))
    if style == "train":
        texture = 0.4 + 1.2 * _decoy_texture(rng, decoy, pts, centre)
    else:
        cells = _maternal_labels(rng, shape, "heldout", int(rng.integers(3, 7)))
        texture = rng.uniform(0.5, 1.5, int(cells.max()) + 1)[cells] * (1 + 0.2 * _smooth_noise(rng, shape, (20, 20, 5)))
    weight = np.clip((1.0 - radius) / 0.15, 0.0, 1.0)                       # a soft edge
    out = background.copy()
    out[box] = (1 - weight) * background[box] + weight * level * rng.uniform(0.6, 1.4) * texture
    return out.astype(np.float32)


def _head_motion(rng: np.random.Generator, slices: int) -> tuple[NDArray, NDArray]:
    """Per-slice rotation ``[n, 3, 3]`` and shift ``[n, 3]`` of the head: a drift plus a few jumps."""
    sigma_deg, sigma_mm = rng.uniform(0, 6), rng.uniform(0, 4)
    rotvec = np.cumsum(rng.normal(0, sigma_deg / 3, (slices, 3)), 0)
    shift = np.cumsum(rng.normal(0, sigma_mm / 3, (slices, 3)), 0)
    jumps = rng.random(slices) < rng.uniform(0, 0.15)
    rotvec[jumps] += rng.normal(0, 12, (int(jumps.sum()), 3))
    shift[jumps] += rng.normal(0, 5, (int(jumps.sum()), 3))
    return Rotation.from_rotvec(np.deg2rad(rotvec - rotvec.mean(0))).as_matrix(), shift - shift.mean(0)


def head_layers(rng: np.random.Generator, thin: bool = False) -> tuple[float, float, float]:
    """The CSF, skull and scalp thicknesses of a head (mm); ``thin`` for a camouflaged head."""
    if thin:
        return rng.uniform(0.3, 1.5), rng.uniform(1.0, 2.5), rng.uniform(0.5, 3.0)
    return rng.uniform(1.0, 3.5), rng.uniform(1.5, 4.0), rng.uniform(2.0, 6.0)


def _head(head: HeadModel, geo: StackGeometry, centre: NDArray, rotation: NDArray, rng: np.random.Generator,
          tissue: dict[str, float], background: NDArray[np.float32], brain_scale: float, gamma: float,
          thin: bool = False, face: Face | None = None, layers: tuple[float, float, float] | None = None,
          ) -> tuple[NDArray, NDArray, NDArray, tuple, tuple]:
    """The head's intensities, skull-inside and brain fractions in its in-plane box of every slice (slice
    profile), the box, and the head's motion (per-slice rotations and shifts); ``thin``: a thin CSF
    layer, skull and scalp (a camouflaged head, :data:`CAMOUFLAGE_SHARE`); ``face``: drawn outside the
    skull, in place of the scalp and the surroundings; ``layers``: the CSF, skull and scalp
    thicknesses (mm; default drawn, :func:`head_layers`)."""
    csf, skull, scalp = layers if layers is not None else head_layers(rng, thin)
    outer = csf + skull + scalp
    reach = max(head.radius_mm * 1.15, face.reach_mm if face is not None else 0.0) + outer + 10.0
    box = geo.box(centre, reach)
    pts = geo.coordinates()[box]                                     # [bx, by, slices, 3]
    rots, shifts = _head_motion(rng, geo.slices)
    values, inside, brain = 0.0, 0.0, 0.0
    offsets = (np.array([-1.0, 0.0, 1.0]) * geo.thickness_mm / 3.0)
    for dz in offsets:
        p = pts + np.array([0, 0, dz], np.float32)
        local = np.einsum("xysc,scd->xysd", p - centre - shifts[None, None], rots) @ rotation
        vox = local @ head.voxel_from_mm[:3, :3].T + head.voxel_from_mm[:3, 3]
        coords = np.moveaxis(vox, -1, 0)
        d = ndimage.map_coordinates(head.sdf, coords, order=1, mode="nearest")
        t2 = ndimage.map_coordinates(head.t2, coords, order=1, mode="constant")
        v = np.where(d <= 0, brain_scale * np.power(np.clip(t2, 1e-3, None), gamma), tissue["csf"])
        v = np.where(d > csf, tissue["skull"], v)
        v = np.where(d > csf + skull, tissue["scalp"], v)
        v = np.where(d > outer, background[box], v)
        if face is not None:
            shown, where = face.render(local)
            v = np.where(where & (d > csf + skull), shown, v)
        values = values + v / len(offsets)
        inside = inside + (d <= csf) / len(offsets)
        brain = brain + (d <= 0) / len(offsets)
    return values, inside, brain, box, (rots, shifts)


@dataclass
class Scene:
    """A synthetic stack and what is true of it.

    Attributes:
        volume: the stack (voxel order ``[x, y, slice]``; voxel -> stack mm).
        mask: everything inside the skull (brain and extra-axial CSF): what the localiser learns,
            as manual fetal brain masks are drawn.
        brain: the atlas's own brain mask carried along (the pose network's mask definition).
        atlas_from_voxel: ``[n, 4, 4]`` each slice's true pose, the stack's voxels -> atlas mm (the
            frame the service's poses are given in); None when the head was scaled.
    """

    volume: Volume
    mask: NDArray[np.bool_]
    brain: NDArray[np.bool_]
    atlas_from_voxel: NDArray[np.float64] | None


def synth_stack(head: HeadModel, rng: np.random.Generator, style: str = "train",
                random_contrast: bool | None = None) -> tuple[Volume, NDArray[np.bool_]]:
    """One synthetic whole-uterus stack and its skull-inside mask (:func:`synth_scene`)."""
    scene = synth_scene(head, rng, style, random_contrast)
    return scene.volume, scene.mask


def synth_scene(head: HeadModel, rng: np.random.Generator, style: str = "train",
                random_contrast: bool | None = None, rigid: bool = False, csf_mm: float | None = None) -> Scene:
    """One synthetic whole-uterus stack, its masks and, with ``rigid`` (the head at the atlas's own
    size, not scaled by 0.9-1.1), its slices' true atlas poses. ``csf_mm``: the extra-axial CSF
    layer this thick instead of drawn (:func:`head_layers`; the other draws stay the same).

    ``random_contrast``: every tissue's intensity drawn uniformly (True) or T2-like (False); by
    default drawn, for 20 % of the ``train`` stacks and half of the ``heldout`` ones. The same seed
    draws the same scene with and without ``rigid`` but for the head's size.
    """
    if style not in STYLES:
        raise ValueError(f"style must be one of {STYLES}")
    geo = StackGeometry.draw(rng)
    if random_contrast is None:
        random_contrast = bool(rng.random() < (0.2 if style == "train" else 0.5))
    tissue = _intensities(rng, random_contrast)
    half_fov = geo.size * geo.pixel_mm / 2.0
    centre = np.array([*rng.uniform(-0.55, 0.55, 2) * max(half_fov - head.radius_mm, 10.0),
                       rng.uniform(-0.3, 0.3) * geo.slices * geo.gap_mm]).astype(np.float32)
    scale = 1.0 if rigid else rng.uniform(0.9, 1.1)
    if rigid:
        rng.uniform(0.9, 1.1)                                   # the same draws after it as without
    rotation = _random_rotation(rng) / scale                    # head frame -> stack frame: rotation @ v
    with_face = bool(rng.random() < FACE_SHARE[style])
    neck = rotation @ NECK_AXIS / np.linalg.norm(rotation @ NECK_AXIS) if with_face else None
    coarse = _surroundings(rng, geo, centre, 0.8 * head.radius_mm * scale, tissue, style, head, neck)
    background = ndimage.zoom(coarse, (2, 2, 1), order=1, grid_mode=True, mode="nearest")[:geo.size, :geo.size]
    brain_scale = tissue["fluid"] * rng.uniform(0.75, 1.05) if rng.random() > 0.15 else rng.uniform(0.2, 1.0)
    gamma = rng.uniform(0.6, 1.6)
    level = brain_scale * float(np.mean(np.power(head.brain_t2, gamma)))       # the brain's mean intensity
    camouflaged = bool(rng.random() < CAMOUFLAGE_SHARE[style])
    if camouflaged:
        background = _camouflage(rng, geo, background, centre, head.radius_mm * scale, level, style, head)
        tissue = {**tissue, "scalp": level * rng.uniform(0.5, 1.2)}
    layers = head_layers(rng, camouflaged)
    if csf_mm is not None:
        layers = (float(csf_mm), *layers[1:])
    face_rng = np.random.default_rng(int(rng.integers(2**31)))     # the same draws after it, with a face or not
    face = Face.draw(face_rng, head, tissue, level, layers[0] + layers[1], style) if with_face else None
    values, inside, brain_fraction, box, motion = _head(head, geo, centre, rotation, rng, tissue, background,
                                                        brain_scale, gamma, camouflaged, face, layers)
    image = background.copy()
    image[box] = values
    mask = np.zeros(image.shape, bool)
    mask[box] = inside >= 0.5
    brain = np.zeros(image.shape, bool)
    brain[box] = brain_fraction >= 0.5
    image *= _bias(rng, image.shape, style)
    image *= _slice_gains(rng, geo.slices)
    sigma = rng.uniform(0.005, 0.08)
    noise = rng.standard_normal(image.shape).astype(np.float32) * sigma
    if style == "train":
        image = np.sqrt((image + noise) ** 2 + (rng.standard_normal(image.shape).astype(np.float32) * sigma) ** 2)
    else:
        image = np.maximum(image + noise, 0)
    affine = np.diag([geo.pixel_mm, geo.pixel_mm, geo.gap_mm, 1.0])
    truth = _slice_poses(head, geo, affine, centre, rotation, *motion) if rigid and head.atlas_from_voxel is not None \
        else None
    return Scene(Volume((image * rng.uniform(100, 2000)).astype(np.float32), affine), mask, brain, truth)


def _slice_poses(head: HeadModel, geo: StackGeometry, affine: NDArray, centre: NDArray, rotation: NDArray,
                 rots: NDArray, shifts: NDArray) -> NDArray[np.float64]:
    """``[n, 4, 4]``: stack voxel -> atlas mm for each slice, the map :func:`_head` samples the head by
    (a stack point ``p``, centred mm, lies at ``(p - centre - shift_k) @ rots_k @ rotation`` in the
    head's centred mm)."""
    stack_mm = np.eye(4)
    stack_mm[:3, 3] = -np.array([(geo.size - 1) / 2.0 * geo.pixel_mm] * 2 + [(geo.slices - 1) / 2.0 * geo.gap_mm])
    out = np.zeros((geo.slices, 4, 4))
    for k in range(geo.slices):
        head_from_stack = np.eye(4)
        a = (rots[k] @ rotation).T
        head_from_stack[:3, :3] = a
        head_from_stack[:3, 3] = -a @ (centre + shifts[k])
        out[k] = head.atlas_from_voxel @ head.voxel_from_mm @ head_from_stack @ stack_mm @ affine
    return out


def _slice_gains(rng: np.random.Generator, slices: int) -> NDArray[np.float32]:
    """Each slice's overall gain: small changes, and for some stacks the odd and even slices of an
    interleaved acquisition apart (spin history), by up to a third."""
    gains = rng.uniform(0.9, 1.1, slices)
    if rng.random() < 0.3:
        gains[::2] *= rng.uniform(0.75, 1.33)
    return gains.astype(np.float32)


def _bias(rng: np.random.Generator, shape: tuple[int, ...], style: str) -> NDArray[np.float32]:
    """A smooth multiplicative field, and for half the stacks the fall-off away from a surface coil
    (up to about x10 across the field of view, as near-coil fat shows in body-array scans)."""
    coil = np.ones(shape[:2] + (1,), np.float32)
    if rng.random() < 0.5:
        axes = np.linspace(-1, 1, shape[0], dtype=np.float32)
        angle = rng.uniform(0, 2 * np.pi)
        towards = np.cos(angle) * axes[:, None] + np.sin(angle) * axes[None, :]
        coil = np.exp(rng.uniform(0.2, 1.2) * towards)[:, :, None].astype(np.float32)
    return coil * _field(rng, shape, style)


def _field(rng: np.random.Generator, shape: tuple[int, ...], style: str) -> NDArray[np.float32]:
    strength = rng.uniform(0.0, 0.6)
    if style == "train":
        return np.exp(strength * _smooth_noise(rng, shape, (3, 3, 2)))
    axes = [np.linspace(-1, 1, s, dtype=np.float32) for s in shape]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    c = rng.normal(0, 1, 6)
    return np.exp(strength * 0.5 * (c[0] * x + c[1] * y + c[2] * z + c[3] * x * x + c[4] * y * y + c[5] * x * y))
