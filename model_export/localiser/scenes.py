"""Synthetic whole-uterus stacks: an atlas brain in generated surroundings (domain randomisation).

A stack is generated in its own frame (``x`` along columns, ``y`` along rows, ``z`` the slice normal,
millimetres, the field of view centred on 0), at a random in-plane pixel size, field of view (mostly
250-400 mm, sometimes cropped to 130-250 mm), slice thickness and slice count, in the way SynthSeg and SynthStrip train on synthetic images:
every tissue's intensity, shape and texture is drawn at random, so that the network learns the
brain's shape and its setting, not one scanner's contrast.

* **Surroundings** (:mod:`model_export.localiser.surroundings`), on a grid of twice the pixel size, made of analytic shapes distorted by smooth
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
  orientation and moves from slice to slice (small drift plus occasional jumps; or, with ``motion``,
  as at a level of the pose benchmarks, over an interleaved acquisition).
* **Hard settings**: some heads sit at or beyond the uterine wall, low in the maternal pelvis
  (:data:`~model_export.localiser.surroundings.ENGAGED_SHARE`); some lie in tissue as bright and as textured as the brain, behind a thin CSF
  layer and skull (:data:`CAMOUFLAGE_SHARE`), so that neither a fluid rim nor a brain brighter than its
  surroundings is what the network learns to look for.
* **Acquisition**: a smooth multiplicative bias field and, for half the stacks, a surface coil's
  fall-off; slice-to-slice intensity changes; noise. With ``shading_share``, that share of the
  stacks also has a dark region fixed in the scanner over part or all of the head
  (:func:`~model_export.localiser.surroundings.shading`: 3 T dielectric shading, signal voids).
  With ``faint_skull_share``, that share of the heads has a skull it hardly shows
  (:data:`FAINT_SKULL_MM` thin at :data:`FAINT_SKULL_OF_FLUID` of the fluid's intensity: a young
  fetus's skull, partial-volumed with the CSF and scalp on a 1.1 mm grid).

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

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.spatial.transform import Rotation

from model_export.acquisitions import MOTION_LEVELS, interleaved_times, motion_twists
from model_export.localiser.head import NECK_AXIS, Face, HeadModel
from model_export.localiser.surroundings import (StackGeometry, bias_field, camouflage, draw_surroundings, intensities,
                                                 random_rotation, shading, slice_gains, smooth_noise)
from service.geometry import se3
from service.io.volume import Volume

STYLES = ("train", "heldout")
MOTIONS = tuple(level for level, limits in MOTION_LEVELS.items() if limits is not None)
"""The pose benchmarks' motion levels a scene's head can move by (``synth_scene(..., motion=)``)."""
FAINT_SKULL_MM = (0.5, 1.0)
"""A faint skull's thickness (mm; :func:`head_layers` draws 1.5-4)."""
FAINT_SKULL_OF_FLUID = (0.4, 0.7)
"""A faint skull's intensity, as a share of the amniotic fluid's (the intensities draw 0-0.15)."""
CAMOUFLAGE_SHARE = {"train": 0.25, "heldout": 0.15}
"""Share of stacks whose head lies in tissue as bright and as textured as the brain, as a head deep in
the maternal pelvis does on a T2 scan: a thin CSF layer and the skull are all that tell where the brain
ends, so the network cannot rely on a fluid rim or on the brain outshining its surroundings."""
FACE_SHARE = {"train": 0.8, "heldout": 0.8}
"""Share of heads drawn with a face (eyes in soft tissue below the frontal lobes) and a neck towards the
trunk; the rest are the bare skull, scalp and a trunk in any direction."""
def _head_motion(rng: np.random.Generator, slices: int, level: str | None = None) -> tuple[NDArray, NDArray]:
    """Per-slice rotation ``[n, 3, 3]`` and shift ``[n, 3]`` of the head: a drift plus a few jumps, or
    with ``level`` the motion of that level of the pose benchmarks
    (:func:`~model_export.acquisitions.motion_twists`) over an interleaved acquisition, about the
    head's centre, drawn from a child of ``rng`` after the drift's draws (the scene's later draws
    stay those it has without)."""
    sigma_deg, sigma_mm = rng.uniform(0, 6), rng.uniform(0, 4)
    rotvec = np.cumsum(rng.normal(0, sigma_deg / 3, (slices, 3)), 0)
    shift = np.cumsum(rng.normal(0, sigma_mm / 3, (slices, 3)), 0)
    jumps = rng.random(slices) < rng.uniform(0, 0.15)
    rotvec[jumps] += rng.normal(0, 12, (int(jumps.sum()), 3))
    shift[jumps] += rng.normal(0, 5, (int(jumps.sum()), 3))
    if level is not None:
        moves = se3.exp(motion_twists(interleaved_times(slices), rng.spawn(1)[0], level))
        return moves[:, :3, :3], moves[:, :3, 3]
    return Rotation.from_rotvec(np.deg2rad(rotvec - rotvec.mean(0))).as_matrix(), shift - shift.mean(0)


def head_layers(rng: np.random.Generator, thin: bool = False) -> tuple[float, float, float]:
    """The CSF, skull and scalp thicknesses of a head (mm); ``thin`` for a camouflaged head."""
    if thin:
        return rng.uniform(0.3, 1.5), rng.uniform(1.0, 2.5), rng.uniform(0.5, 3.0)
    return rng.uniform(1.0, 3.5), rng.uniform(1.5, 4.0), rng.uniform(2.0, 6.0)


def csf_patches(rng: np.random.Generator, head: HeadModel, widest_mm: float,
                patch_mm: float = 25.0) -> NDArray[np.float32]:
    """Where and by how much (mm, on the head's grid) the extra-axial CSF is wider than its layer: smooth
    patches about ``patch_mm`` across, up to ``widest_mm``, over about half the brain's surface. A
    real fetal head's CSF is not one even layer: cisterns, the Sylvian fissures' openings and the
    wide spaces of younger fetuses hold centimetres of it in places and little elsewhere.

    Example:
        >>> head = HeadModel.from_arrays(np.ones((20, 20, 20)), np.ones((20, 20, 20)), np.diag([2.0, 2, 2, 1]))
        >>> extra = csf_patches(np.random.default_rng(0), head, 6.0)
        >>> extra.shape == head.sdf.shape, bool(extra.min() >= 0 and extra.max() <= 6.0)
        (True, True)
    """
    spacing = 1.0 / np.abs(np.diag(head.voxel_from_mm)[:3])
    cells = tuple(max(2, int(round(n * s / patch_mm))) for n, s in zip(head.sdf.shape, spacing))
    noise = smooth_noise(rng, head.sdf.shape, cells)
    return (widest_mm * np.clip(noise, 0.0, 2.0) / 2.0).astype(np.float32)


def _head(head: HeadModel, geo: StackGeometry, centre: NDArray, rotation: NDArray, rng: np.random.Generator,
          tissue: dict[str, float], background: NDArray[np.float32], brain_scale: float, gamma: float,
          thin: bool = False, face: Face | None = None, layers: tuple[float, float, float] | None = None,
          csf_extra: NDArray | None = None, motion: str | None = None) -> tuple[NDArray, NDArray, NDArray, tuple, tuple]:
    """The head's intensities, skull-inside and brain fractions in its in-plane box of every slice (slice
    profile), the box, and the head's motion (per-slice rotations and shifts); ``thin``: a thin CSF
    layer, skull and scalp (a camouflaged head, :data:`CAMOUFLAGE_SHARE`); ``face``: drawn outside the
    skull, in place of the scalp and the surroundings; ``layers``: the CSF, skull and scalp
    thicknesses (mm; default drawn, :func:`head_layers`); ``csf_extra``: mm of CSF added to the layer
    where the head's grid says (the shape of ``head.sdf``; :func:`csf_patches`), the skull and scalp
    pushed out by as much; ``motion``: a pose benchmark's motion level instead of the drift
    (:func:`_head_motion`)."""
    csf, skull, scalp = layers if layers is not None else head_layers(rng, thin)
    outer = csf + skull + scalp
    widest = float(csf_extra.max()) if csf_extra is not None else 0.0
    reach = max(head.radius_mm * 1.15, face.reach_mm if face is not None else 0.0) + outer + widest + 10.0
    box = geo.box(centre, reach)
    pts = geo.coordinates()[box]                                     # [bx, by, slices, 3]
    rots, shifts = _head_motion(rng, geo.slices, motion)
    values, inside, brain = 0.0, 0.0, 0.0
    offsets = (np.array([-1.0, 0.0, 1.0]) * geo.thickness_mm / 3.0)
    for dz in offsets:
        p = pts + np.array([0, 0, dz], np.float32)
        local = np.einsum("xysc,scd->xysd", p - centre - shifts[None, None], rots) @ rotation
        vox = local @ head.voxel_from_mm[:3, :3].T + head.voxel_from_mm[:3, 3]
        coords = np.moveaxis(vox, -1, 0)
        d = ndimage.map_coordinates(head.sdf, coords, order=1, mode="nearest")
        if csf_extra is not None:              # the layers measured from the widened CSF's edge
            d = np.where(d > 0, np.maximum(d - ndimage.map_coordinates(csf_extra, coords, order=1, mode="nearest"),
                                           1e-3), d)
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
    look: Look | None = None
    """The contrast and head layers it was drawn with: another stack of the same scan is drawn with
    them (``look``)."""


@dataclass(frozen=True)
class Look:
    """What every stack of one scan shares: each tissue's intensity, the brain's scale and the gamma
    of its T2 map (the contrast), and the layers about the fetus's head."""

    tissue: dict[str, float]
    brain_scale: float
    gamma: float
    layers: tuple[float, float, float] | None = None
    """The head's CSF, skull and scalp thicknesses (mm; :func:`head_layers`): one head's in every stack."""


def synth_stack(head: HeadModel, rng: np.random.Generator, style: str = "train",
                random_contrast: bool | None = None, shading_share: float = 0.0,
                faint_skull_share: float = 0.0, motion: str | None = None) -> tuple[Volume, NDArray[np.bool_]]:
    """One synthetic whole-uterus stack and its skull-inside mask (:func:`synth_scene`)."""
    scene = synth_scene(head, rng, style, random_contrast, shading_share=shading_share,
                        faint_skull_share=faint_skull_share, motion=motion)
    return scene.volume, scene.mask


def synth_scene(head: HeadModel, rng: np.random.Generator, style: str = "train",
                random_contrast: bool | None = None, rigid: bool = False, csf_mm: float | None = None,
                shading_share: float = 0.0, csf_patches_mm: float = 0.0, faint_skull_share: float = 0.0,
                motion: str | None = None, look: Look | None = None,
                orientation: NDArray | None = None) -> Scene:
    """One synthetic whole-uterus stack, its masks and, with ``rigid`` (the head at the atlas's own
    size, not scaled by 0.9-1.1), its slices' true atlas poses. ``csf_mm``: the extra-axial CSF
    layer this thick instead of drawn (:func:`head_layers`; the other draws stay the same).
    ``shading_share``: the chance of a dark region over the head (:func:`~model_export.localiser.surroundings.shading`;
    at 0, the default, nothing is drawn for it, so a seed gives the stack it gave without it).
    ``csf_patches_mm``: the CSF layer widened in patches by up to this much (:func:`csf_patches`,
    drawn from a child of ``rng``: the scene is otherwise the one the seed gives without them).
    ``faint_skull_share``: the chance of a thin skull of nearly the fluid's intensity
    (:data:`FAINT_SKULL_MM`, :data:`FAINT_SKULL_OF_FLUID`; drawn from a child of ``rng``, so the
    scene is otherwise the one the seed gives without it).
    ``motion``: the head moves as at that level of the pose benchmarks (``mild``, ``moderate``,
    ``jumps``, ``independent``; :func:`~model_export.acquisitions.motion_twists`) over an
    interleaved acquisition, instead of the generator's own drift (from a child of ``rng``: the
    scene is otherwise the one the seed gives without it).

    ``look``: the contrast and head layers of another stack of the same scan (:attr:`Scene.look`)
    instead of those drawn (the draws are made all the same: the scene is otherwise the one the seed
    gives without it).

    ``orientation``: the head's axes in the stack (``[3, 3]``, head frame -> stack frame), as a
    radiographer plans a stack about the fetal head, instead of drawn (the draw is made all the
    same: the scene is otherwise the one the seed gives without it).

    ``random_contrast``: every tissue's intensity drawn uniformly (True) or T2-like (False); by
    default drawn, for 20 % of the ``train`` stacks and half of the ``heldout`` ones. The same seed
    draws the same scene with and without ``rigid`` but for the head's size.
    """
    if style not in STYLES:
        raise ValueError(f"style must be one of {STYLES}")
    if motion is not None and motion not in MOTIONS:
        raise ValueError(f"motion must be one of {MOTIONS} (or None: the generator's own drift)")
    geo = StackGeometry.draw(rng)
    if random_contrast is None:
        random_contrast = bool(rng.random() < (0.2 if style == "train" else 0.5))
    tissue = intensities(rng, random_contrast)
    half_fov = geo.size * geo.pixel_mm / 2.0
    centre = np.array([*rng.uniform(-0.55, 0.55, 2) * max(half_fov - head.radius_mm, 10.0),
                       rng.uniform(-0.3, 0.3) * geo.slices * geo.gap_mm]).astype(np.float32)
    scale = 1.0 if rigid else rng.uniform(0.9, 1.1)
    if rigid:
        rng.uniform(0.9, 1.1)                                   # the same draws after it as without
    rotation = random_rotation(rng) / scale                    # head frame -> stack frame: rotation @ v
    if orientation is not None:
        rotation = np.asarray(orientation, np.float64) / scale
    with_face = bool(rng.random() < FACE_SHARE[style])
    neck = rotation @ NECK_AXIS / np.linalg.norm(rotation @ NECK_AXIS) if with_face else None
    coarse = draw_surroundings(rng, geo, centre, 0.8 * head.radius_mm * scale, tissue, style, head, neck)
    background = ndimage.zoom(coarse, (2, 2, 1), order=1, grid_mode=True, mode="nearest")[:geo.size, :geo.size]
    brain_scale = tissue["fluid"] * rng.uniform(0.75, 1.05) if rng.random() > 0.15 else rng.uniform(0.2, 1.0)
    gamma = rng.uniform(0.6, 1.6)
    if look is not None:
        tissue, brain_scale, gamma = dict(look.tissue), look.brain_scale, look.gamma
    contrast = (dict(tissue), float(brain_scale), float(gamma))
    level = brain_scale * float(np.mean(np.power(head.brain_t2, gamma)))       # the brain's mean intensity
    camouflaged = bool(rng.random() < CAMOUFLAGE_SHARE[style])
    if camouflaged:
        background = camouflage(rng, geo, background, centre, head.radius_mm * scale, level, style, head)
        tissue = {**tissue, "scalp": level * rng.uniform(0.5, 1.2)}
    layers = head_layers(rng, camouflaged)
    if csf_mm is not None:
        layers = (float(csf_mm), *layers[1:])
    if look is not None and look.layers is not None:
        layers = look.layers
    drawn = Look(*contrast, layers=tuple(float(t) for t in layers))
    faint = rng.spawn(1)[0] if faint_skull_share > 0 else None           # the scene's own draws untouched
    if faint is not None and faint.random() < faint_skull_share:
        layers = (layers[0], float(faint.uniform(*FAINT_SKULL_MM)), layers[2])
        tissue = {**tissue, "skull": tissue["fluid"] * float(faint.uniform(*FAINT_SKULL_OF_FLUID))}
    face_rng = np.random.default_rng(int(rng.integers(2**31)))     # the same draws after it, with a face or not
    face = Face.draw(face_rng, head, tissue, level, layers[0] + layers[1], style) if with_face else None
    extra = csf_patches(rng.spawn(1)[0], head, csf_patches_mm) if csf_patches_mm > 0 else None   # the stream untouched
    values, inside, brain_fraction, box, motion = _head(head, geo, centre, rotation, rng, tissue, background,
                                                        brain_scale, gamma, camouflaged, face, layers, extra, motion)
    image = background.copy()
    image[box] = values
    mask = np.zeros(image.shape, bool)
    mask[box] = inside >= 0.5
    brain = np.zeros(image.shape, bool)
    brain[box] = brain_fraction >= 0.5
    image *= bias_field(rng, image.shape, style)
    image *= slice_gains(rng, geo.slices)
    if shading_share > 0 and rng.random() < shading_share:
        image *= shading(rng, geo, centre, head.radius_mm * scale)
    sigma = rng.uniform(0.005, 0.08)
    noise = rng.standard_normal(image.shape).astype(np.float32) * sigma
    if style == "train":
        image = np.sqrt((image + noise) ** 2 + (rng.standard_normal(image.shape).astype(np.float32) * sigma) ** 2)
    else:
        image = np.maximum(image + noise, 0)
    affine = np.diag([geo.pixel_mm, geo.pixel_mm, geo.gap_mm, 1.0])
    truth = _slice_poses(head, geo, affine, centre, rotation, *motion) if rigid and head.atlas_from_voxel is not None \
        else None
    return Scene(Volume((image * rng.uniform(100, 2000)).astype(np.float32), affine), mask, brain, truth, drawn)


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
