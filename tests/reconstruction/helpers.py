"""Small phantom acquisitions for the reconstruction tests (fixed seeds, a few seconds to build).

Three orthogonal stacks of thick slices (Gaussian through-plane profile, FWHM = slice spacing) are
acquired from :func:`tests.support.phantoms.phantom_brain` with known per-slice rigid motion; the true
``atlas_from_voxel`` of slice ``s`` is ``motion[s] @ stack_affine``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from service.geometry import se3, sampling
from service.geometry.pose import make_pose
from service.io.volume import Volume
from service.reconstruction.grid import Grid
from service.reconstruction.slices import SliceSet
from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine

CENTRE = np.array([0.0, 3.0, 8.0])


@dataclass
class Acquisition:
    """Phantom, stacks and true transforms."""

    image: np.ndarray
    mask: np.ndarray
    affine: np.ndarray
    stacks: list[tuple[Volume, np.ndarray]]
    truth: list[np.ndarray]            # per stack [n, 4, 4] true atlas_from_voxel

    def slice_set(self, poses: list[np.ndarray] | None = None, include: list[np.ndarray] | None = None) -> SliceSet:
        poses = self.truth if poses is None else poses
        include = [np.ones(len(p), bool) for p in poses] if include is None else include
        return SliceSet.from_stacks([(v, m, p, i) for (v, m), p, i in zip(self.stacks, poses, include)])

    @property
    def true_poses(self) -> np.ndarray:
        return np.concatenate(self.truth)


def rigid_about(centre: np.ndarray, rot_deg: np.ndarray, trans_mm: np.ndarray) -> np.ndarray:
    """Rigid transforms ``[n, 4, 4]`` rotating by rotation vectors (degrees) about ``centre``, then translating."""
    rot = se3.so3_exp(np.deg2rad(rot_deg))
    to_c = make_pose(np.eye(3), centre)
    return to_c @ make_pose(rot, trans_mm) @ se3.inverse(to_c)


def random_motion(n: int, rng: np.random.Generator, rot_deg: float, trans_mm: float) -> np.ndarray:
    """Per-slice rigid motion about the phantom's centre: normal rotation vectors and translations."""
    return rigid_about(CENTRE, rng.normal(scale=rot_deg, size=(n, 3)), rng.normal(scale=trans_mm, size=(n, 3)))


def thick_stack(image: np.ndarray, mask: np.ndarray, atlas_affine: np.ndarray, affine: np.ndarray,
                shape: tuple[int, int, int], axis: int, motion: np.ndarray, psf_points: int = 9) -> tuple:
    """``acquire_stack`` through a Gaussian PSF: FWHM = the slice spacing through-plane, 1.2 pixels in-plane.

    The through-plane profile is integrated by ``psf_points`` samples over +-3 sigma (9: a variance
    within 1 % of the Gaussian's), independent of the service's own quadrature; the in-plane blur
    is applied to the acquired slices.
    """
    sigma_vox = sampling.FWHM_TO_SIGMA            # FWHM of one slice spacing, in voxel units
    u = np.linspace(-3.0, 3.0, psf_points)
    w = np.exp(-0.5 * u**2)
    w /= w.sum()
    img = np.zeros(shape, np.float32)
    for ui, wi in zip(u, w):
        shift = np.eye(4)
        shift[axis, 3] = ui * sigma_vox
        img += wi * acquire_stack(image, mask, atlas_affine, affine @ shift, shape, axis, motion)[0]
    _, msk = acquire_stack(image, mask, atlas_affine, affine, shape, axis, motion)
    inplane = np.full(3, sampling.INPLANE_FWHM_FACTOR * sampling.FWHM_TO_SIGMA)   # pixels
    inplane[axis] = 0.0
    return ndimage.gaussian_filter(img, inplane, mode="constant"), msk


def textured_brain(seed: int, texture: float = 25.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`phantom_brain` (small) plus band-limited texture inside the brain.

    The plain phantom is piecewise constant: a slice that cuts no blob carries no information about
    its position, so registration could not be judged on it. The texture (unit-variance Gaussian
    noise smoothed at 1.5 voxels, times ``texture``) stands in for the gyri, sulci and tissue contrast
    of a real brain.
    """
    image, mask, aff = phantom_brain(seed, shape=(44, 48, 44), spacing=1.6, radii_mm=(24.0, 29.0, 26.0))
    rng = np.random.default_rng(seed + 1000)
    tex = ndimage.gaussian_filter(rng.normal(size=image.shape), 1.5)
    tex *= texture / tex.std()
    image = np.where(mask > 0, np.maximum(image + tex, 1.0), 0.0)
    return ndimage.gaussian_filter(image, 0.5).astype(np.float32), mask, aff


def make_acquisition(seed: int = 0, rot_deg: float = 1.0, trans_mm: float = 1.0, noise: float = 1.0,
                     shape: tuple[int, int, int] = (48, 48, 20), inplane_mm: float = 1.5,
                     thickness_mm: float = 3.0) -> Acquisition:
    """Three orthogonal stacks (slice axes 2, 1, 0; slightly oblique) of a small phantom brain."""
    rng = np.random.default_rng(seed)
    image, mask, aff = textured_brain(seed)
    stacks, truth = [], []
    for axis, rv in zip((2, 1, 0), ([0.05, 0.0, 0.0], [0.0, 0.0, 0.08], [0.0, -0.06, 0.0])):
        shp = list(shape[:2])
        shp.insert(axis, shape[2])
        shp = tuple(shp)
        saff = stack_affine(axis, se3.so3_exp(np.array(rv)), inplane_mm, thickness_mm, shp, CENTRE)
        motion = random_motion(shp[axis], rng, rot_deg, trans_mm)
        img, msk = thick_stack(image, mask, aff, saff, shp, axis, motion)
        img = img + rng.normal(scale=noise, size=img.shape).astype(np.float32) * (img > 0)
        stacks.append((Volume(img, saff), msk))
        truth.append(motion @ saff)
    return Acquisition(image, mask, aff, stacks, truth)


def perturb(poses: np.ndarray, rng: np.random.Generator, rot_deg: float, trans_mm: float,
            centres: np.ndarray) -> np.ndarray:
    """Left-compose each pose with a random rigid error about its slice centre ``centres [n, 3]``.

    Rotation vectors (degrees) and translations (mm) are normal with the given scale per axis.
    """
    n = len(poses)
    rot = se3.so3_exp(np.deg2rad(rng.normal(scale=rot_deg, size=(n, 3))))
    c = np.asarray(centres, dtype=np.float64)
    t = c + rng.normal(scale=trans_mm, size=(n, 3)) - np.einsum("nij,nj->ni", rot, c)
    return make_pose(rot, t) @ poses


def pose_error_mm(slices: SliceSet, estimate: np.ndarray, truth: np.ndarray, which: np.ndarray | None = None) -> float:
    """Mean distance (mm) between each pixel's position under ``estimate`` and under ``truth``."""
    d = np.linalg.norm(slices.positions(estimate) - slices.positions(truth), axis=1)
    keep = np.ones(len(d), bool) if which is None else which[slices.slice_id]
    return float(d[keep].mean())


def reference_on(grid: Grid, acq: Acquisition) -> tuple[np.ndarray, np.ndarray]:
    """The phantom and its brain mask resampled to ``grid`` (trilinear)."""
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in grid.shape], indexing="ij"), -1).astype(np.float64)
    pts = ijk @ grid.affine[:3, :3].T + grid.affine[:3, 3]
    ref = sampling.sample_points(acq.image, acq.affine, pts)
    msk = sampling.sample_points(acq.mask, acq.affine, pts) > 0.5
    return ref, msk


def psnr_ncc(volume: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """PSNR (dB, peak = reference max in the mask, after a least-squares linear intensity fit) and NCC."""
    x = volume[mask].astype(np.float64)
    y = reference[mask].astype(np.float64)
    a, b = np.polyfit(x, y, 1)
    mse = np.mean((a * x + b - y) ** 2)
    psnr = 10.0 * np.log10(y.max() ** 2 / mse)
    ncc = float(np.corrcoef(x, y)[0, 1])
    return float(psnr), ncc


def relative_pose_error_mm(slices: SliceSet, estimate: np.ndarray, truth: np.ndarray,
                           which: np.ndarray | None = None) -> float:
    """:func:`pose_error_mm` after removing the rigid offset common to all slices (robust fit).

    A reconstruction keeps the frame of its input poses; the common offset of their errors is
    invisible to it. ``which`` restricts both the fit and the mean to those slices.
    """
    from service.reconstruction.registration import anchor_frame

    w = None if which is None else np.asarray(which, np.float64)
    return pose_error_mm(slices, anchor_frame(slices, truth, estimate, w), truth, which)
