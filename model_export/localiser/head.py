"""The fetal head of a synthetic whole-uterus stack: an atlas brain ready for sampling, and a face.

:class:`HeadModel` holds one atlas brain as :mod:`model_export.localiser.scenes` samples it (its T2
intensities and the signed distance to its mask, in millimetres from its centre); :class:`Face` a face
and a neck drawn about it (two fluid-filled eyes in textured soft tissue below the frontal lobes, a neck
leaving the skull base), which on a T2 scan look much like a piece of brain right under it.

Example:
    >>> mask = np.zeros((20, 24, 22), np.float32); mask[4:16, 5:19, 4:18] = 1
    >>> head = HeadModel.from_arrays(mask * 1000.0, mask, np.diag([2.0, 2.0, 2.0, 1.0]))
    >>> head.half_extent_mm.round(1).tolist(), round(head.radius_mm, 1)
    ([11.0, 13.0, 13.0], 21.4)
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from model_export.atlas import signed_distance

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
