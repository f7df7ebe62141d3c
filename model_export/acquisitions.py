"""Simulated 3-stack acquisitions with exact per-slice ground truth, for tests and evaluation.

An acquisition is three stacks (axial, coronal, sagittal with respect to the brain, each tilted
by up to :data:`STACK_TILT_DEG`), 3 mm slices 3 mm apart on a square in-plane grid, acquired
interleaved (even slices first), with a smooth bias field and Rician noise, placed in a scanner
frame at a random rigid position of the fetus (any orientation; the brain anywhere within
:data:`SCANNER_ORIGIN_MM` of the scanner's origin per axis: a whole-uterus field of view off the
isocentre, or the origin another pipeline's files choose). The fetus moves during the acquisition:

* ``mild``: a smooth random trajectory reaching 5 deg / 3 mm at its largest;
* ``moderate``: the same reaching 20 deg / 8 mm;
* ``jumps``: smooth drift (10 deg / 4 mm) with sudden jumps: at 1-4 random moments the fetus
  moves to a new position (up to 20 deg and 8 mm per axis from the stack's) and stays there;
* ``independent``: every slice an independent draw, uniform within 20 deg and 8 mm per axis
  (no temporal smoothness at all);
* ``extreme``: an independent random orientation (and a position within 15 mm of the brain
  centre) for every slice.

Each slice's truth is its ``atlas_from_voxel`` (voxel ``(i, j, k)`` of THAT slice -> atlas mm),
exactly what ``/v1/predict`` returns. Numpy only (the service's sampler); the volume may be an
atlas volume or a phantom.

Example:
    >>> import numpy as np
    >>> vol = np.zeros((40, 40, 40), np.float32); vol[10:30, 12:28, 14:26] = 100.0
    >>> aff = np.diag([2.0, 2.0, 2.0, 1.0]); aff[:3, 3] = -39.0
    >>> stacks = simulate_acquisition(vol, vol > 0, aff, np.random.default_rng(0), "mild", size=24, pixel_mm=2.0)
    >>> [s.orientation for s in stacks], stacks[0].volume.array.shape[:2]
    (['axial', 'coronal', 'sagittal'], (24, 24))
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from service.geometry import iterators, sampling, se3
from service.geometry.pose import index_reversal, make_pose, translate
from service.io.volume import Volume
from service.preprocess.stack import split_stack

JUMP_DEG, JUMP_MM = 20.0, 8.0
"""Largest rotation angle and translation per axis of a jump, and of an ``independent`` slice."""
MOTION_LEVELS: dict[str, tuple[float, float] | None] = {
    "mild": (5.0, 3.0), "moderate": (20.0, 8.0), "jumps": (10.0, 4.0), "independent": (JUMP_DEG, JUMP_MM),
    "extreme": None}
"""Largest rotation (deg) and translation (mm) of each level's motion (for ``jumps``, of its smooth
drift); ``None``: any orientation per slice."""
MAX_JUMPS = 4
STACK_TILT_DEG = 10.0
EXTREME_OFFSET_MM = 15.0
SCANNER_ORIGIN_MM = 150.0
ORIENTATIONS = {
    # columns: the stack's in-plane x, in-plane y and normal, as atlas directions
    "axial": np.eye(3),
    "coronal": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
    "sagittal": np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
}


@dataclass
class SimulatedStack:
    """One simulated stack as a file would hold it, with its truth.

    Attributes:
        volume: the stack in scanner RAS (``[W, W, n]``, slice axis last).
        mask: the brain mask on the same grid.
        atlas_from_voxel: ``[n, 4, 4]`` exact per-slice truth.
        orientation: ``axial``, ``coronal`` or ``sagittal``.
        times: ``[n]`` acquisition time (order) of each slice.
        motion: the motion level.
    """

    volume: Volume
    mask: Volume
    atlas_from_voxel: NDArray[np.float64]
    orientation: str
    times: NDArray[np.int64]
    motion: str


def interleaved_times(n: int) -> NDArray[np.int64]:
    """Acquisition order of an interleaved stack: even slices first, then odd ones."""
    k = np.arange(n)
    return np.where(k % 2 == 0, k // 2, (n + 1) // 2 + k // 2)


def stored_last_to_first(stack: SimulatedStack) -> SimulatedStack:
    """The same stack as a file that stores its slices the other way writes it: the slice axis
    reversed in the voxels and the affine (each slice where it was), the truth and the acquisition
    times with it. An interleaved acquisition then runs downwards in the file's slice order.

    Example:
        >>> s = SimulatedStack(Volume(np.arange(3.0).reshape(1, 1, 3), np.eye(4)), Volume(np.ones((1, 1, 3)), np.eye(4)),
        ...                    np.stack([translate([0, 0, k]) for k in range(3)]), "axial", interleaved_times(3), "mild")
        >>> r = stored_last_to_first(s)
        >>> r.volume.array.ravel().tolist(), r.times.tolist(), float((r.volume.affine @ [0, 0, 0, 1])[2])
        ([2.0, 1.0, 0.0], [1, 2, 0], 2.0)
        >>> bool(np.allclose(r.atlas_from_voxel[0] @ [0, 0, 0, 1], s.atlas_from_voxel[2] @ [0, 0, 2, 1]))
        True
    """
    flip = index_reversal(2, stack.volume.array.shape[2])
    return SimulatedStack(Volume(stack.volume.array[:, :, ::-1].copy(), stack.volume.affine @ flip),
                          Volume(stack.mask.array[:, :, ::-1].copy(), stack.mask.affine @ flip),
                          stack.atlas_from_voxel[::-1] @ flip, stack.orientation, stack.times[::-1].copy(), stack.motion)


def smooth_motion(times: ArrayLike, rng: np.random.Generator, max_deg: float, max_mm: float) -> NDArray[np.float64]:
    """Twists ``[n, 6]`` of a smooth random trajectory over acquisition ``times``, scaled to its maxima.

    Each of the six components is a sum of three sinusoids of random phase over the acquisition;
    the rotation vector's largest norm is ``max_deg`` and the translation's ``max_mm``.
    """
    t = np.asarray(times, dtype=np.float64) / max(1.0, float(np.max(times)))
    freq = np.arange(1, 4)[:, None, None]
    amp = rng.normal(0.0, 1.0, (3, 1, 6)) / freq
    phase = rng.uniform(0, 2 * np.pi, (3, 1, 6))
    xi = np.sum(amp * np.sin(2 * np.pi * freq * 0.5 * t[None, :, None] + phase), axis=0)   # [n, 6]
    xi -= xi.mean(axis=0)
    rot = np.linalg.norm(xi[:, :3], axis=1).max()
    tra = np.linalg.norm(xi[:, 3:], axis=1).max()
    xi[:, :3] *= np.radians(max_deg) / max(rot, 1e-12)
    xi[:, 3:] *= max_mm / max(tra, 1e-12)
    return xi


def uniform_twists(n: int, rng: np.random.Generator, max_deg: float, max_mm: float) -> NDArray[np.float64]:
    """``[n, 6]`` independent twists: a rotation about a random axis by up to ``max_deg`` (uniform
    angle) and a translation uniform within ``max_mm`` along each axis."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = rng.uniform(-np.radians(max_deg), np.radians(max_deg), (n, 1))
    return np.concatenate([axis * angle, rng.uniform(-max_mm, max_mm, (n, 3))], axis=1)


def motion_twists(times: ArrayLike, rng: np.random.Generator, motion: str) -> NDArray[np.float64]:
    """Twists ``[n, 6]`` (about the brain centre, scanner axes) of one stack's slices acquired at
    ``times`` under a smooth or jumping motion level (see the module docstring; not ``extreme``).

    Example:
        >>> tw = motion_twists(np.arange(20), np.random.default_rng(0), "jumps")
        >>> jumps = np.linalg.norm(np.diff(tw[np.argsort(np.arange(20))], axis=0), axis=1)
        >>> bool(jumps.max() > 5 * np.median(jumps))                   # a few large steps, many small
        True
    """
    t = np.asarray(times)
    max_deg, max_mm = MOTION_LEVELS[motion]
    if motion == "independent":
        return uniform_twists(len(t), rng, max_deg, max_mm)
    drift = smooth_motion(t, rng, max_deg, max_mm)
    if motion != "jumps":
        return drift
    moments_after = np.arange(1, max(len(t), 2))                       # a jump between two acquisitions
    count = min(int(rng.integers(1, MAX_JUMPS + 1)), len(moments_after))
    moments = np.sort(rng.choice(moments_after, size=count, replace=False))
    segment = np.searchsorted(moments, t, side="right")                 # 0 before the first jump
    offsets = np.concatenate([np.zeros((1, 6)), uniform_twists(count, rng, JUMP_DEG, JUMP_MM)])
    return se3.log(se3.exp(offsets[segment]) @ se3.exp(drift))


def stack_axes(orientation: str, rng: np.random.Generator) -> NDArray[np.float64]:
    """``[3, 3]`` a stack's axes (columns: in-plane x, in-plane y, normal; atlas directions) as
    planned about the fetal head: the ``orientation``'s, tilted by a random rotation of about
    :data:`STACK_TILT_DEG` (the planning's error, the head's move since).

    Example:
        >>> axes = stack_axes("sagittal", np.random.default_rng(0))
        >>> bool(np.allclose(axes.T @ axes, np.eye(3))), bool(abs(axes[0, 2]) > 0.9)    # normal near left-right
        (True, True)
    """
    tilt = se3.so3_exp(rng.normal(0, 1, 3) * np.radians(STACK_TILT_DEG) / np.sqrt(3))
    return tilt @ ORIENTATIONS[orientation]


def simulate_stack(image: NDArray, mask: NDArray, affine: NDArray, centre: NDArray, orientation: str,
                   scanner_from_atlas: NDArray, rng: np.random.Generator, motion: str, *, size: int = 128,
                   pixel_mm: float = 1.0, gap_mm: float = 3.0, thickness_mm: float = 3.0, noise: float = 0.03,
                   bias: float = 0.2, axes: NDArray | None = None) -> SimulatedStack:
    """One stack through ``centre`` (atlas mm) in ``orientation``; see the module docstring. ``axes``:
    the stack's axes (:func:`stack_axes`' columns) instead of the orientation's planned ones (the
    planning's draw is made all the same)."""
    rot = stack_axes(orientation, rng)
    if axes is not None:
        rot = np.asarray(axes, np.float64)
    n = int(np.ceil(_brain_extent(mask, affine, rot[:, 2]) / gap_mm)) + 2
    spacing = np.array([pixel_mm, pixel_mm, gap_mm])
    static = make_pose(rot, centre) @ translate(-(np.array([size, size, n]) - 1) / 2.0 * spacing) @ np.diag([*spacing, 1.0])
    times = interleaved_times(n)
    file_affine = scanner_from_atlas @ static
    stack_geo = split_stack(Volume(np.zeros((size, size, n), np.float32), file_affine), np.ones((size, size, n), bool))
    level = MOTION_LEVELS[motion]
    if level is None:
        poses = iterators.random_poses(n, rng, tz_max_mm=0.0, centre=np.zeros(3))
        poses[:, :3, 3] = centre + rng.uniform(-EXTREME_OFFSET_MM, EXTREME_OFFSET_MM, (n, 3))
        truth = poses @ stack_geo.slice_from_voxel
    else:
        about_centre = translate(centre) @ se3.exp(motion_twists(times, rng, motion)) @ translate(-centre)
        truth = about_centre @ static[None]
    slice_poses = truth @ np.linalg.inv(stack_geo.slice_from_voxel)        # slice frame -> atlas, rigid
    img = sampling.sample_slices(image, affine, slice_poses, size, pixel_mm, thickness_mm=thickness_mm or None)
    msk = sampling.sample_slices(mask.astype(np.float32), affine, slice_poses, size, pixel_mm) > 0.5
    img = _corrupt(img, rng, noise, bias) if noise or bias else img
    # each picture back in the file's voxel order, as the service's slices lay it out (split_stack)
    array = np.ascontiguousarray(stack_geo.to_stack(img).astype(np.float32))
    marray = np.ascontiguousarray(stack_geo.to_stack(msk).astype(np.uint8))
    return SimulatedStack(Volume(array, file_affine), Volume(marray, file_affine), truth, orientation, times, motion)


def simulate_acquisition(image: NDArray, mask: NDArray, affine: NDArray, rng: np.random.Generator,
                         motion: str = "mild", axes: list[NDArray | None] | None = None,
                         **kwargs: float) -> list[SimulatedStack]:
    """Axial, coronal and sagittal stacks of one volume, one fetus position in the scanner; ``axes``: each
    stack's axes instead of its planned ones (:func:`simulate_stack`; the draws are made all the same)."""
    if motion not in MOTION_LEVELS:
        raise ValueError(f"unknown motion level {motion!r}; expected one of {list(MOTION_LEVELS)}")
    m = np.asarray(mask) > 0.5
    centre = _centroid(m, affine)
    scanner_from_atlas = make_pose(iterators.random_rotations(1, rng, np.pi)[0], rng.uniform(-SCANNER_ORIGIN_MM, SCANNER_ORIGIN_MM, 3))
    return [simulate_stack(np.asarray(image, np.float32), m, affine, centre, o, scanner_from_atlas, rng, motion,
                           axes=a, **kwargs) for o, a in zip(ORIENTATIONS, axes or [None] * len(ORIENTATIONS))]


def _centroid(mask: NDArray, affine: NDArray) -> NDArray:
    idx = np.argwhere(mask).mean(axis=0)
    return affine[:3, :3] @ idx + affine[:3, 3]


def _brain_extent(mask: NDArray, affine: NDArray, normal: NDArray) -> float:
    pts = np.argwhere(mask)[::50] @ affine[:3, :3].T + affine[:3, 3]
    proj = pts @ normal
    return float(proj.max() - proj.min())


def _corrupt(img: NDArray, rng: np.random.Generator, noise: float, bias: float) -> NDArray:
    """A smooth multiplicative bias field over the stack and Rician noise (sigma relative to p99)."""
    field = ndimage.gaussian_filter(rng.normal(0, 1, img.shape), sigma=(2.0, img.shape[1] / 4, img.shape[2] / 4))
    field = np.exp(bias * field / max(np.abs(field).max(), 1e-12))
    scale = float(np.percentile(img, 99)) or 1.0
    signal = img * field
    sigma = noise * scale
    return np.sqrt((signal + rng.normal(0, sigma, img.shape)) ** 2 + rng.normal(0, sigma, img.shape) ** 2)
