"""Training-slice simulation: realistic thick, noisy, bias-shaded slices cut at any angle.

A batch is made per volume, as a scanner would acquire it, then put through EXACTLY the service's
slice preprocessing (:func:`service.preprocess.slices.preprocess_slices`):

1. poses from the paper's iterators (random, Euler or Fibonacci; full 360 degree in-plane range),
   ``Tz`` within 94 % of the brain's extent along the slice normal (``tz_fraction``);
2. acquisition on an ``H x H`` grid of ``0.8-1.5`` mm pixels with a Gaussian thick-slice PSF
   (``2-4.5`` mm FWHM through-plane, ``1.2 x`` pixel in-plane), by trilinear interpolation in
   PyTorch (``grid_sample``); brain size varies by +-10 % (the atlas is sampled with pixels ``1/k``
   smaller than declared, which is a brain ``k`` times larger);
3. smooth multiplicative bias, gamma, occasional signal voids, Rician noise; the mask is perturbed
   (blurred and re-thresholded) like an imperfect localisation and, for a share of the slices
   (``mask_wobble_share``), its boundary moved in and out by a smooth random field of up to
   ``mask_wobble_px`` pixels about an offset drawn from ``mask_offset_px``: the bites and bulges of a learned localiser's mask (a missed lobe, the
   eyes below the frontal lobes); a share of the slices (``surroundings_share``) shows a head's
   surroundings outside the brain instead of the skull-stripped atlas's black (a CSF layer, the
   skull, the scalp and textured tissue with fluid pockets, by the 3D distance to the brain), so
   a mask larger than the brain shows what it would show in a scan;
4. mask, 1/99 % rescale to 0-255, resample to the model grid centred on the mask centroid; the label
   is the atlas pose of the CENTRED slice (the label moves with the crop).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import NDArray
from scipy import ndimage
from scipy.special import expit

from model_export.atlas import AtlasVolume, signed_distance
from service.geometry import iterators, sampling
from service.inference.acceptance import MIN_MASK_FRACTION
from service.geometry.pose import make_pose, slice_pixel_coordinates
from service.preprocess.slices import preprocess_slices


PSF_POINTS = 5
"""Through-plane Gaussian quadrature points (+-2 sigma) of the simulated thick-slice PSF."""


INPLANE_SIGMA_PX = sampling.INPLANE_FWHM_FACTOR * sampling.FWHM_TO_SIGMA
"""The acquisition's in-plane blur (Gaussian sigma, acquisition pixels), of the slices and of the
surroundings drawn round them."""
DISTANCE_PAD_MM = 20.0
"""How far round an atlas's crop its brain's distance map is computed; beyond it the map is held
(every layer of :func:`dress` lies within 13.5 mm of the brain)."""


FULL_EXTENT_TZ_FRACTION = 0.47
"""Training planes cover 94 % of the brain's extent along their normal. A real stack covers the whole
brain: about a quarter of its slices lie beyond the central 70 % (``iterators.TZ_FRACTION``, the
paper's range and the standard validation's), and a network that never sees such planes is lost
there (the twin-min E.D. by depth is in docs/accuracy.md)."""


@dataclass
class SimulationConfig:
    """Ranges of the simulated acquisition; each value is drawn uniformly per slice or per batch."""

    size: int = 96
    pixel_mm: float = 1.25
    fov_mm: float = 140.0
    acq_pixel_mm: tuple[float, float] = (0.8, 1.5)
    thickness_mm: tuple[float, float] = (2.0, 4.5)
    brain_scale: tuple[float, float] = (0.9, 1.1)
    noise: tuple[float, float] = (0.0, 0.08)
    bias: float = 0.35
    gamma: tuple[float, float] = (0.75, 1.35)
    void_probability: float = 0.1
    shading_ball_probability: float = 0.0
    shading_ball_radius_mm: tuple[float, float] = (8.0, 30.0)
    shading_ball_gain: tuple[float, float] = (0.3, 0.7)
    shading_ball_edge_mm: tuple[float, float] = (1.0, 4.0)
    mask_threshold: tuple[float, float] = (0.3, 0.7)
    mask_blur_px: float = 1.5
    mask_wobble_share: float = 0.0
    mask_wobble_px: tuple[float, float] = (0.0, 0.0)
    mask_wobble_cells_px: float = 12.0
    mask_offset_px: tuple[float, float] = (0.0, 0.0)
    surroundings_share: float = 0.0
    sampling: str = "random"
    inplane_range: float = 2 * np.pi
    tz_fraction: float = FULL_EXTENT_TZ_FRACTION
    min_mask_fraction: float = MIN_MASK_FRACTION    # the slices the service poses, not fewer

    @classmethod
    def validation(cls, **overrides: object) -> "SimulationConfig":
        """The fixed evaluation setting: 3 mm thick, 1.0 mm pixels, moderate noise and bias, no voids,
        planes in the central 70 % of the brain (the paper's range; ``tz_fraction=0.5`` for all of it)."""
        base = dict(acq_pixel_mm=(1.0, 1.0), thickness_mm=(3.0, 3.0), brain_scale=(1.0, 1.0),
                    noise=(0.03, 0.03), bias=0.2, gamma=(1.0, 1.0), void_probability=0.0,
                    mask_threshold=(0.5, 0.5), tz_fraction=iterators.TZ_FRACTION)
        base.update(overrides)
        return cls(**base)  # type: ignore[arg-type]


def shading_ball(b: int, h: int, config: SimulationConfig, rng: np.random.Generator) -> NDArray[np.float64]:
    """``[b, h, h]`` gains: in a ``config.shading_ball_probability`` share of the slices, the cross-section
    of a dark ball that sits still in the scanner (what N4 leaves of 3 T dielectric shading): a disc of
    ``shading_ball_radius_mm`` about a point within 30 mm of the brain's centre, its signal times
    ``shading_ball_gain``, with a logistic edge of ``shading_ball_edge_mm``; 1 elsewhere. The
    Gaussian ``void_probability`` blobs are smaller and softer than such a ball.

    Example:
        >>> g = shading_ball(4, 96, SimulationConfig(shading_ball_probability=1.0), np.random.default_rng(0))
        >>> g.shape, bool(g.min() < 0.75), float(g.max()) <= 1.0
        ((4, 96, 96), True, True)
    """
    gain = np.ones((b, h, h))
    if config.shading_ball_probability <= 0.0:          # no draw: the other draws stay as they were
        return gain
    dark = rng.random(b) < config.shading_ball_probability
    if not dark.any():
        return gain
    k = int(dark.sum())
    half_mm = config.size * config.pixel_mm / 2.0
    u = np.linspace(-half_mm, half_mm, h)
    yy, xx = np.meshgrid(u, u, indexing="ij")
    cy, cx = rng.uniform(-30.0, 30.0, size=(2, k, 1, 1))
    radius = rng.uniform(*config.shading_ball_radius_mm, size=(k, 1, 1))
    floor = rng.uniform(*config.shading_ball_gain, size=(k, 1, 1))
    edge = rng.uniform(*config.shading_ball_edge_mm, size=(k, 1, 1))
    r = np.hypot(xx - cx, yy - cy)
    gain[dark] = floor + (1.0 - floor) * expit((r - radius) / edge)
    return gain


def wobble_masks(masks: NDArray[np.bool_], config: SimulationConfig, rng: np.random.Generator) -> NDArray[np.bool_]:
    """``masks [B, H, W]`` with the boundary of a ``config.mask_wobble_share`` of them moved by a smooth
    field: each pixel is kept where its signed distance to the boundary (px, < 0 inside) is below
    ``o + a * f``, ``f`` smooth unit-variance noise of ``mask_wobble_cells_px`` correlation, ``a``
    drawn from ``mask_wobble_px`` and ``o`` (a dilation when positive) from ``mask_offset_px`` per
    slice. The largest piece is kept, its holes filled.

    Example:
        >>> m = np.zeros((1, 64, 64), bool); m[0, 16:48, 16:48] = True
        >>> cfg = SimulationConfig(mask_wobble_share=1.0, mask_wobble_px=(4.0, 4.0))
        >>> w = wobble_masks(m, cfg, np.random.default_rng(0))
        >>> bool((w != m).any()), bool(w[0, 32, 32])
        (True, True)
    """
    if config.mask_wobble_share <= 0:
        return masks                 # no draw: with the option off the random stream, so every slice, stays as it was
    which = np.flatnonzero(rng.random(len(masks)) < config.mask_wobble_share)
    if which.size == 0 or (config.mask_wobble_px[1] <= 0 and not any(config.mask_offset_px)):
        return masks
    out = masks.copy()
    noise = ndimage.gaussian_filter(rng.standard_normal((which.size, *masks.shape[1:])),
                                    (0.0, config.mask_wobble_cells_px, config.mask_wobble_cells_px))
    noise /= np.maximum(noise.reshape(which.size, -1).std(1), 1e-9)[:, None, None]
    amplitude = rng.uniform(*config.mask_wobble_px, size=which.size)
    offset = rng.uniform(*config.mask_offset_px, size=which.size)
    for j, i in enumerate(which):
        m = masks[i]
        if not m.any() or m.all():
            continue
        moved = signed_distance(m) < offset[j] + amplitude[j] * noise[j]
        labels, n = ndimage.label(moved)
        if n == 0:
            continue
        largest = labels == 1 + int(np.argmax(ndimage.sum_labels(moved, labels, range(1, n + 1))))
        out[i] = ndimage.binary_fill_holes(largest)
    return out


def dress(images: NDArray[np.float32], brain: NDArray[np.float32], distance_mm: NDArray[np.float32],
          rng: np.random.Generator, share: float, blur_px: float = 0.0) -> NDArray[np.float32]:
    """Skull-stripped slices ``images [B, H, W]`` with a head's surroundings drawn outside the brain
    on a ``share`` of them: by the brain's signed distance ``distance_mm`` (< 0 inside), a CSF layer
    (0.5-3.5 mm, as bright as the brain's brightest), the skull (1-4 mm, dark), the scalp (1-6 mm)
    and beyond, textured soft tissue with fluid pockets; levels relative to each slice's brain (its
    99th percentile inside ``brain`` > 0.5), blended by ``1 - brain`` (the brain's partial volume)
    and blurred in-plane by ``blur_px`` like the acquisition.

    Example:
        >>> yy, xx = np.mgrid[:48, :48]
        >>> d = (np.hypot(yy - 24, xx - 24) - 12.0)[None].astype(np.float32)          # a disc of 12 px
        >>> brain = (d < 0).astype(np.float32); img = 100.0 * brain
        >>> out = dress(img, brain, d, np.random.default_rng(0), share=1.0)
        >>> bool(np.all(out[d < 0] == 100.0)), bool(out[0, 24, 37] > 50.0), bool(out[0, 0, 0] > 0.0)
        (True, True, True)
    """
    which = np.flatnonzero(rng.random(len(images)) < share)
    out = np.array(images, dtype=np.float32, copy=True)
    if not which.size:
        return out
    shape = (which.size, *images.shape[1:])
    layers = np.cumsum(rng.uniform([0.5, 1.0, 1.0], [3.5, 4.0, 6.0], size=(which.size, 3)), axis=1)[:, :, None, None]
    levels = rng.uniform([0.7, 0.0, 0.2, 0.1, 0.7], [1.3, 0.25, 0.8, 1.0, 1.3], size=(which.size, 5))[:, :, None, None]
    cells = rng.uniform(2.0, 8.0)
    texture = ndimage.gaussian_filter(rng.standard_normal(shape), (0.0, cells, cells))
    texture /= np.maximum(texture.reshape(which.size, -1).std(1), 1e-9)[:, None, None]
    coarse = (which.size, *(-(-np.array(shape[1:]) // 4)))              # fluid pockets: 4x coarser, then up
    pockets = ndimage.gaussian_filter(rng.standard_normal(coarse), (0.0, 0.75 * cells, 0.75 * cells))
    pockets = F.interpolate(torch.from_numpy(pockets[:, None]), scale_factor=4, mode="bilinear",
                            align_corners=False)[:, 0, :shape[1], :shape[2]].numpy()
    pockets /= np.maximum(pockets.reshape(which.size, -1).std(1), 1e-9)[:, None, None]
    tissue = levels[:, 3] * (1.0 + rng.uniform(0.1, 0.5, (which.size, 1, 1)) * texture)
    tissue = np.where(pockets > rng.uniform(0.8, 3.0, (which.size, 1, 1)), levels[:, 4], tissue)
    d = distance_mm[which]
    around = np.where(d < layers[:, 0], levels[:, 0], np.where(d < layers[:, 1], levels[:, 1],
                      np.where(d < layers[:, 2], levels[:, 2], tissue)))
    if blur_px > 0:
        around = ndimage.gaussian_filter(around, (0.0, blur_px, blur_px))
    inside = brain[which] > 0.5
    ref = np.array([np.percentile(im[m], 99.0) if m.any() else 0.0 for im, m in zip(images[which], inside)])
    out[which] = images[which] + (1.0 - np.clip(brain[which], 0.0, 1.0)) * np.maximum(around, 0.0) * ref[:, None, None]
    return out


@dataclass
class SliceBatch:
    """Network inputs with their labels and the acquisition that made them."""

    inputs: NDArray[np.float32]           # [B, L, L], 0-255
    poses: NDArray[np.float64]            # [B, 4, 4] atlas pose of each centred network input
    volume: list[str] = field(default_factory=list)
    thickness_mm: NDArray[np.float64] | None = None


def sample_slices_torch(volume: torch.Tensor, affine: NDArray, poses: NDArray, size: int, pixel_mm: float,
                        offsets_mm: NDArray | None = None, weights: NDArray | None = None,
                        padding_mode: str = "zeros") -> torch.Tensor:
    """Trilinear slices ``[B, C, L, L]`` of ``volume [1, C, I, J, K]`` at ``poses``, optionally PSF-weighted.

    The same forward model as :func:`service.geometry.sampling.sample_slices` (whose tests pin it
    down), in PyTorch for speed: ``grid_sample`` with ``align_corners=True`` indexes voxel centres.
    """
    if offsets_mm is None:
        offsets_mm, weights = np.zeros(1), np.ones(1)
    # The map slice mm (x, y, z) -> grid_sample's normalised (k, j, i) coordinates is affine per pose:
    # columns c0, c1, c2 and offset d. Built in float64 (tiny), applied in float32 by broadcasting.
    vox_from_slice = np.linalg.inv(affine) @ poses                                  # [B, 4, 4]
    shape = np.array(volume.shape[2:], dtype=np.float64)
    norm = np.diag(np.append(2.0 / (shape - 1.0), 1.0))
    norm[:3, 3] = -1.0
    lin = (norm @ vox_from_slice)[:, [2, 1, 0], :]                                   # [B, 3 (k, j, i), 4]
    lin_t = torch.from_numpy(lin.astype(np.float32))
    xy = torch.from_numpy(slice_pixel_coordinates(size, pixel_mm).astype(np.float32))     # [L, L, 2]
    plane = xy[None, ..., 0:1] * lin_t[:, None, None, :, 0] + xy[None, ..., 1:2] * lin_t[:, None, None, :, 1]
    z = torch.from_numpy(np.asarray(offsets_mm, dtype=np.float32))                      # plane: [B, L, L, 3]
    shift = z[None, :, None] * lin_t[:, None, :, 2] + lin_t[:, None, :, 3]                # [B, O, 3]
    grid = (plane[:, None] + shift[:, :, None, None, :]).reshape(1, -1, size, size, 3)
    out = F.grid_sample(volume, grid, mode="bilinear", padding_mode=padding_mode, align_corners=True)
    out = out.reshape(volume.shape[1], len(poses), len(offsets_mm), size, size)
    w = torch.from_numpy(np.asarray(weights, dtype=np.float32))
    return torch.einsum("cbors,o->bcrs", out, w)


@dataclass
class Acquisition:
    """Clean thick slices of one volume before corruption (reusable: corruption is redrawn)."""

    images: NDArray[np.float32]
    masks: NDArray[np.float32]
    poses: NDArray[np.float64]          # atlas poses of the acquisition planes
    pixel_mm: float                     # declared (subject) pixel size
    thickness_mm: float
    scale: float                        # brain size factor k (atlas sampled at pixel_mm / k)
    volume: str
    distance_mm: NDArray[np.float32] | None = None     # signed distance to the brain (surroundings)


class SliceSimulator:
    """Draws batches of simulated, preprocessed slices with their centred atlas poses."""

    def __init__(self, volumes: list[AtlasVolume], config: SimulationConfig | None = None) -> None:
        self.volumes = volumes
        self.config = config or SimulationConfig()
        self._tensors = [(torch.from_numpy(v.image)[None, None], torch.from_numpy(v.mask)[None, None])
                         for v in volumes]
        self._grids: dict[str, NDArray] = {}
        self._distances: dict[int, tuple[torch.Tensor, NDArray]] = {}

    # ---- poses ------------------------------------------------------------------------------
    def _rotations(self, n: int, rng: np.random.Generator) -> NDArray:
        c = self.config
        if c.sampling == "random":
            return iterators.random_rotations(n, rng, c.inplane_range)
        if c.sampling not in self._grids:
            if c.sampling == "euler":
                grid = iterators.euler_grid(tz_max_mm=0.0, tz_step_mm=1.0)
            elif c.sampling == "fibonacci":
                grid = iterators.fibonacci_grid(tz_max_mm=0.0, tz_step_mm=1.0, inplane_range=c.inplane_range)
            else:
                raise ValueError(f"unknown sampling {c.sampling!r}; expected random, euler or fibonacci")
            self._grids[c.sampling] = grid[:, :3, :3]
        grid = self._grids[c.sampling]
        return grid[rng.integers(0, len(grid), n)]

    def sample_poses(self, vol: AtlasVolume, n: int, rng: np.random.Generator) -> NDArray[np.float64]:
        """Atlas poses of ``n`` acquisition planes through ``vol``: Tz within ``2 tz_fraction`` of the
        brain's extent along the normal, about its middle."""
        rot = self._rotations(n, rng)
        lo, hi = vol.extent_along(rot[:, :, 2])
        mid, half = (lo + hi) / 2.0, (hi - lo) / 2.0
        tz = mid + rng.uniform(-1.0, 1.0, n) * 2.0 * self.config.tz_fraction * half
        return make_pose(rot, vol.centre + rot[:, :, 2] * tz[:, None])

    # ---- acquisition and corruption -----------------------------------------------------------
    def acquire(self, index: int, poses: NDArray, acq_pixel_mm: float, thickness_mm: float,
                scale: float = 1.0) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Thick slices and their (thin, centre-plane) masks ``[B, H, H]`` of volume ``index``."""
        vol = self.volumes[index]
        h = int(np.ceil(self.config.fov_mm / acq_pixel_mm / 2.0)) * 2
        sigma = thickness_mm / scale * sampling.FWHM_TO_SIGMA
        offsets = np.linspace(-2.0 * sigma, 2.0 * sigma, PSF_POINTS)
        weights = np.exp(-0.5 * (offsets / sigma) ** 2)
        image, mask = self._tensors[index]
        img = sample_slices_torch(image, vol.affine, poses, h, acq_pixel_mm / scale, offsets,
                                  weights / weights.sum())[:, 0].numpy()
        msk = sample_slices_torch(mask, vol.affine, poses, h, acq_pixel_mm / scale)[:, 0].numpy()
        return ndimage.gaussian_filter(img, (0.0, INPLANE_SIGMA_PX, INPLANE_SIGMA_PX), mode="constant"), msk

    def distance(self, index: int, poses: NDArray, acq_pixel_mm: float, scale: float = 1.0) -> NDArray[np.float32]:
        """``[B, H, H]`` the signed distance (atlas mm, < 0 inside) to volume ``index``'s brain on the
        centre planes :meth:`acquire` samples; the distance map is padded by :data:`DISTANCE_PAD_MM`
        round the atlas's crop and held beyond it."""
        if index not in self._distances:
            vol = self.volumes[index]
            spacing = np.sqrt((vol.affine[:3, :3] ** 2).sum(0))
            pad = np.ceil(DISTANCE_PAD_MM / spacing).astype(int)
            inside = np.pad(vol.mask > 0.5, [(p, p) for p in pad])
            affine = vol.affine.copy()
            affine[:3, 3] -= vol.affine[:3, :3] @ pad
            self._distances[index] = (torch.from_numpy(signed_distance(inside, spacing))[None, None], affine)
        signed, affine = self._distances[index]
        h = int(np.ceil(self.config.fov_mm / acq_pixel_mm / 2.0)) * 2
        out = sample_slices_torch(signed, affine, poses, h, acq_pixel_mm / scale, padding_mode="border")
        return out[:, 0].numpy()

    def corrupt(self, img: NDArray, mask: NDArray, rng: np.random.Generator,
                distance_mm: NDArray | None = None) -> tuple[NDArray, NDArray]:
        """Surroundings (with ``distance_mm``, :func:`dress`), bias, gamma, signal voids, Rician
        noise; an imperfect mask."""
        c = self.config
        b, h, _ = img.shape
        if distance_mm is not None and c.surroundings_share > 0:
            img = dress(img, mask, distance_mm, rng, c.surroundings_share, INPLANE_SIGMA_PX)
        u = np.linspace(-1.0, 1.0, h)
        yy, xx = np.meshgrid(u, u, indexing="ij")
        basis = np.stack([xx, yy, xx * xx, yy * yy, xx * yy])                       # [5, H, H]
        coef = rng.normal(scale=c.bias / 2.0, size=(b, 5))
        img = img * np.exp(np.einsum("bk,khw->bhw", coef, basis))
        img = img * shading_ball(b, h, c, rng)
        scale = np.maximum(np.percentile(img.reshape(b, -1), 99.5, axis=1), 1e-6)[:, None, None]
        img = np.clip(img / scale, 0.0, None) ** rng.uniform(*c.gamma, size=(b, 1, 1))
        voids = rng.random(b) < c.void_probability
        if voids.any():
            cy, cx = rng.uniform(-0.4, 0.4, size=(2, b, 1, 1))
            r = rng.uniform(0.05, 0.2, size=(b, 1, 1))
            blob = np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * r * r))
            img = np.where(voids[:, None, None], img * (1.0 - 0.9 * blob), img)
        sd = rng.uniform(*c.noise, size=(b, 1, 1))
        img = np.sqrt((img + sd * rng.normal(size=img.shape)) ** 2 + (sd * rng.normal(size=img.shape)) ** 2)
        soft = ndimage.gaussian_filter(mask, (0.0, c.mask_blur_px, c.mask_blur_px))
        mask = soft > rng.uniform(*c.mask_threshold, size=(b, 1, 1))
        return img.astype(np.float32), wobble_masks(mask, c, rng)

    def acquisition(self, index: int, n: int, rng: np.random.Generator) -> "Acquisition":
        """``n`` clean thick slices of volume ``index`` at random poses with one random acquisition
        setting (pixel size, thickness, brain scale), with the brain's distance where surroundings are drawn."""
        c = self.config
        vol = self.volumes[index]
        poses = self.sample_poses(vol, n, rng)
        acq = float(rng.uniform(*c.acq_pixel_mm))
        thick = float(rng.uniform(*c.thickness_mm))
        k = float(rng.uniform(*c.brain_scale))
        img, mask = self.acquire(index, poses, acq, thick, k)
        distance = self.distance(index, poses, acq, k) if c.surroundings_share > 0 else None
        return Acquisition(img, mask, poses, acq, thick, k, vol.name, distance)

    def simulate(self, index: int, n: int, rng: np.random.Generator) -> SliceBatch:
        """``n`` preprocessed slices from volume ``index`` with one acquisition setting."""
        return self.finish(self.acquisition(index, n, rng), rng)

    def finish(self, acq: "Acquisition", rng: np.random.Generator) -> SliceBatch:
        """Corrupt an acquisition (fresh draws every call) and preprocess it as the service does."""
        img, mask = self.corrupt(acq.images, acq.masks, rng, acq.distance_mm)
        prep = preprocess_slices(img, mask, (acq.pixel_mm, acq.pixel_mm), self.config.size, self.config.pixel_mm)
        labels = sampling.recentre(acq.poses, prep.centroid_mm / acq.scale)
        keep = prep.mask_fraction >= self.config.min_mask_fraction
        return SliceBatch(prep.inputs[keep], labels[keep], [acq.volume] * int(keep.sum()),
                          np.full(int(keep.sum()), acq.thickness_mm))

    def batch(self, n: int, rng: np.random.Generator, volumes_per_batch: int = 4) -> SliceBatch:
        """A batch of about ``n`` slices from ``volumes_per_batch`` random volumes."""
        picks = rng.choice(len(self.volumes), size=min(volumes_per_batch, len(self.volumes)), replace=False)
        parts = [self.simulate(int(i), int(np.ceil(n / len(picks))), rng) for i in picks]
        return SliceBatch(np.concatenate([p.inputs for p in parts])[:n], np.concatenate([p.poses for p in parts])[:n],
                          sum((p.volume for p in parts), [])[:n],
                          np.concatenate([p.thickness_mm for p in parts])[:n])
