"""The world around a synthetic fetal head: the stack's geometry, tissue intensities, the mother's body,
uterus, placenta, amniotic fluid and the fetal body, camouflaging tissue, and the acquisition's
intensity fields (:mod:`model_export.localiser.scenes` puts the head in it).

Everything is drawn from the generator it is given, in a fixed order, so a seed gives one scene. Two
styles differ in everything here (``"train"``: maternal labels from the arg-max of smooth noise
fields, a smooth-noise bias; ``"heldout"``: Voronoi cells, a polynomial bias), so that a validation
set of the held-out style measures generalisation rather than memory of the generator.

Example:
    >>> import numpy as np
    >>> geo = StackGeometry(pixel_mm=2.0, size=64, thickness_mm=3.0, gap_mm=3.0, slices=10)
    >>> rng = np.random.default_rng(0)
    >>> image = draw_surroundings(rng, geo, np.zeros(3), 40.0, intensities(rng, False), "train")
    >>> image.shape, image.dtype
    ((32, 32, 10), dtype('float32'))
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.spatial.transform import Rotation

if TYPE_CHECKING:
    from model_export.localiser.head import HeadModel

ENGAGED_SHARE = {"train": 0.3, "heldout": 0.25}
"""Share of stacks whose head sits at or beyond the uterine wall (late pregnancy, head in the maternal
pelvis): the scalp meets maternal tissue or the wall, with little or no amniotic fluid around it."""


def random_rotation(rng: np.random.Generator) -> NDArray[np.float64]:
    return Rotation.random(random_state=int(rng.integers(2**31))).as_matrix()


def smooth_noise(rng: np.random.Generator, shape: tuple[int, ...], cells: tuple[int, ...]) -> NDArray[np.float32]:
    """Zero-mean, unit-scale smooth noise on ``shape``: Gaussian noise on ``cells`` points, upsampled."""
    small = rng.standard_normal(cells).astype(np.float32)
    out = ndimage.zoom(small, [s / c for s, c in zip(shape, cells)], order=1, mode="nearest", grid_mode=True)
    return out[tuple(slice(0, s) for s in shape)]


def _ellipsoid_radius(points: NDArray, centre: NDArray, axes: NDArray, rotation: NDArray) -> NDArray[np.float32]:
    """Normalised radius of ``points [..., 3]`` in an ellipsoid (1 on its surface)."""
    local = (points - centre) @ rotation / axes
    return np.sqrt((local ** 2).sum(-1)).astype(np.float32)


def intensities(rng: np.random.Generator, random_contrast: bool) -> dict[str, float]:
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
        fields = np.stack([smooth_noise(rng, shape, (rng.integers(4, 12),) * 2 + (rng.integers(2, 5),))
                           for _ in range(count)])
        return np.argmax(fields, 0).astype(np.int8)
    small = tuple(max(2, s // 4) for s in shape)
    seeds = rng.uniform(0, 1, (count * 6, 3)) * np.array(small)
    grid = np.stack(np.meshgrid(*[np.arange(s, dtype=np.float32) for s in small], indexing="ij"), -1)
    cells = (np.argmin(((grid[..., None, :] - seeds) ** 2).sum(-1), axis=-1) % count).astype(np.int8)
    out = ndimage.zoom(cells, [s / c for s, c in zip(shape, small)], order=0, grid_mode=True, mode="nearest")
    return out[tuple(slice(0, s) for s in shape)]


def draw_surroundings(rng: np.random.Generator, geo: StackGeometry, brain_centre: NDArray, head_radius: float,
                  tissue: dict[str, float], style: str, decoy: HeadModel | None = None,
                  neck: NDArray | None = None) -> NDArray[np.float32]:
    """The scene without the head, on the half-resolution grid ``[n, n, slices]``; ``neck``: the
    direction (stack frame) the fetal trunk lies in from the head, roughly (default any)."""
    pts = geo.coordinates(step=2)
    shape = pts.shape[:3]
    def wobble(amount: float) -> NDArray[np.float32]:
        return amount * smooth_noise(rng, shape, (5, 5, 3))
    # the mother: an ellipsoid body, air outside, a fat layer under the skin, tissues inside
    body_r = _ellipsoid_radius(pts, rng.normal(0, 30, 3), rng.uniform([150, 110, 150], [230, 180, 260]),
                               random_rotation(rng)) + wobble(0.03)
    fat_depth = rng.uniform(0.04, 0.15)
    n_labels = int(rng.integers(3, 7))
    labels = _maternal_labels(rng, shape, style, n_labels)
    means = rng.uniform(0.02, 0.9, n_labels) if style == "heldout" else \
        np.concatenate([[tissue["fat"]], rng.uniform(0.02, 0.7, n_labels - 1)])
    image = means[labels].astype(np.float32) * (1 + 0.25 * smooth_noise(rng, shape, (24, 24, 6)))
    if rng.random() < 0.5:                                   # bowel gas and fluid-filled loops: small blobs
        blobs = smooth_noise(rng, shape, (40, 40, 8))
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
    rot = random_rotation(rng)
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
    image = np.where(placenta, tissue["placenta"] * (1 + 0.15 * smooth_noise(rng, shape, (20, 20, 5))), image)
    fluid = tissue["fluid"] * (1 + rng.uniform(0, 0.1) * smooth_noise(rng, shape, (8, 8, 3)))
    image = np.where(uterus_r <= 1 - wall, fluid, image)
    trunk_rot = Rotation.align_vectors([direction], [[1.0, 0.0, 0.0]])[0].as_matrix()
    body = _ellipsoid_radius(pts, trunk_c, np.array([length, *rng.uniform(0.5, 0.9, 2) * head_radius]),
                             trunk_rot) + wobble(0.05) <= 1
    for _ in range(int(rng.integers(0, 5))):
        c = trunk_c + rng.normal(0, 1, 3) * length
        body |= _ellipsoid_radius(pts, c, rng.uniform(6, 25, 3), random_rotation(rng)) <= 1
    body_texture = tissue["body"] * (1 + 0.3 * smooth_noise(rng, shape, (30, 30, 8)))
    if decoy is not None and rng.random() < 0.6:               # organs as rich in texture as a brain
        body_texture = tissue["body"] * (0.4 + 1.2 * _decoy_texture(rng, decoy, pts, trunk_c))
    local = (pts - trunk_c) @ trunk_rot                           # the spine: a dark rod along the trunk
    spine = (np.hypot(local[..., 1] - rng.uniform(-0.5, 0.5) * head_radius, local[..., 2]) < rng.uniform(3, 7)) \
        & (np.abs(local[..., 0]) < length)
    body_texture = np.where(spine, tissue["skull"], body_texture)
    for _ in range(int(rng.integers(0, 4))):                       # stomach, bladder, heart: fluid-like blobs
        c = trunk_c + (rng.uniform(-0.6, 0.6, 3) * [length, 0.4 * head_radius, 0.4 * head_radius]) @ trunk_rot.T
        blob = _ellipsoid_radius(pts, c, rng.uniform(6, 18, 3), random_rotation(rng)) <= 1
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
    local = ((pts - centre) @ random_rotation(rng)) * rng.uniform(0.6, 1.4)
    folded = np.abs(np.mod(local + half, 4 * half) - 2 * half) - half       # a mirror tiling of the cube
    vox = folded @ head.voxel_from_mm[:3, :3].T + head.voxel_from_mm[:3, 3]
    t2 = ndimage.map_coordinates(head.t2, np.moveaxis(vox, -1, 0), order=1, mode="nearest")
    return np.clip(t2, 0, 1.2).astype(np.float32) ** rng.uniform(0.7, 1.4)


def camouflage(rng: np.random.Generator, geo: StackGeometry, background: NDArray[np.float32], centre: NDArray,
                head_radius: float, level: float, style: str, decoy: HeadModel) -> NDArray[np.float32]:
    """``background`` with the tissue around the head (a distorted ellipsoid 1.2-2x the head's
    radius) replaced by tissue of the brain's ``level`` times 0.6-1.4, textured: the atlas interior
    folded and tiled (``train``) or Voronoi-like cells of random intensities (``heldout``)."""
    reach = 2.0 * head_radius + 10.0
    box = geo.box(centre, reach)
    pts = geo.coordinates()[box]
    shape = pts.shape[:3]
    radius = _ellipsoid_radius(pts, centre, head_radius * rng.uniform(1.2, 2.0, 3), random_rotation(rng)) \
        + 0.15 * smooth_noise(rng, shape, (6, 6, 3))
    if style == "train":
        texture = 0.4 + 1.2 * _decoy_texture(rng, decoy, pts, centre)
    else:
        cells = _maternal_labels(rng, shape, "heldout", int(rng.integers(3, 7)))
        texture = rng.uniform(0.5, 1.5, int(cells.max()) + 1)[cells] * (1 + 0.2 * smooth_noise(rng, shape, (20, 20, 5)))
    weight = np.clip((1.0 - radius) / 0.15, 0.0, 1.0)                       # a soft edge
    out = background.copy()
    out[box] = (1 - weight) * background[box] + weight * level * rng.uniform(0.6, 1.4) * texture
    return out.astype(np.float32)


def slice_gains(rng: np.random.Generator, slices: int) -> NDArray[np.float32]:
    """Each slice's overall gain: small changes, and for some stacks the odd and even slices of an
    interleaved acquisition apart (spin history), by up to a third."""
    gains = rng.uniform(0.9, 1.1, slices)
    if rng.random() < 0.3:
        gains[::2] *= rng.uniform(0.75, 1.33)
    return gains.astype(np.float32)


def bias_field(rng: np.random.Generator, shape: tuple[int, ...], style: str) -> NDArray[np.float32]:
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
        return np.exp(strength * smooth_noise(rng, shape, (3, 3, 2)))
    axes = [np.linspace(-1, 1, s, dtype=np.float32) for s in shape]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    c = rng.normal(0, 1, 6)
    return np.exp(strength * 0.5 * (c[0] * x + c[1] * y + c[2] * z + c[3] * x * x + c[4] * y * y + c[5] * x * y))


def shading(rng: np.random.Generator, geo: StackGeometry, head_centre: NDArray, head_radius: float) -> NDArray[np.float32]:
    """A dark region fixed in the scanner over part or all of the fetal head, as 3 T dielectric
    shading and signal voids leave one in real whole-uterus stacks (a stack of another site shows the
    head at 0.35-0.5 x its median over a third of the brain): a turned ellipsoid of 0.5-1.8 head radii,
    centred within a head radius of the head's centre, whose gain falls to 0.2-0.7 inside over a soft
    edge of 2-15 mm. Returned on the stack's grid ``[size, size, slices]``, to multiply the image by.

    Example (the gain is lowest inside and 1 far away):
        >>> geo = StackGeometry(2.0, 100, 3.0, 3.0, 20)
        >>> g = shading(np.random.default_rng(0), geo, np.zeros(3), 45.0)
        >>> g.shape, bool(g.min() < 0.75), bool(np.isclose(g.max(), 1.0, atol=0.05))
        ((100, 100, 20), True, True)
    """
    radius = head_radius * rng.uniform(0.5, 1.8)
    axes = radius * rng.uniform(0.7, 1.4, 3)
    direction = rng.normal(size=3)
    centre = np.asarray(head_centre, np.float64) + direction / np.linalg.norm(direction) * rng.uniform(0.0, 1.0) * head_radius
    floor, edge = rng.uniform(0.2, 0.7), rng.uniform(2.0, 15.0)
    distance = (_ellipsoid_radius(geo.coordinates(), centre, axes, random_rotation(rng)) - 1.0) * radius
    return (floor + (1.0 - floor) / (1.0 + np.exp(-distance / edge))).astype(np.float32)
