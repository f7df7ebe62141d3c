"""Batched rigid slice-to-volume registration: all slices at once, maximising per-slice NCC.

For slice ``i`` with (subsampled) pixel values ``s_k`` and simulated values ``m_k`` (the volume,
blurred by the in-plane PSF, averaged over the through-plane PSF points of each pixel), the
objective is ``NCC_i = sum s~_k m~_k / (|s~| |m~|)`` (``~``: minus the slice mean). Its derivative
with respect to each simulated value is closed-form,

    dNCC/dm_k = (s~_k - (A / B) m~_k) / (|s~| sqrt(B)),   A = sum s~ m~,  B = sum m~^2,

and a rigid perturbation ``x -> R(omega)(x - c_i) + c_i + t`` of the slice about its centre ``c_i``
moves every sample point ``x``, so (with ``g = grad V(x)`` from the exact trilinear derivative)

    dNCC/dt = sum_k dNCC/dm_k g_k,    dNCC/domega = sum_k dNCC/dm_k (x_k - c_i) x g_k.

Every iteration takes, for every slice still moving, a Levenberg-Marquardt step on these analytic
derivatives (the Gauss-Newton matrix of ``2 - 2 NCC``, also accumulated per slice with ``bincount``),
clipped to the slice's trust radius in the metric where 1 mm of translation counts as much as 1
degree of rotation; it evaluates the NCC (and its derivatives) at the trial poses of all those
slices in one vectorised pass, keeps the step where the NCC improved and, where it did not, halves
the radius and raises the damping. The radius starts at 1 mm / 1 deg and a slice stops when it
falls below 0.1 mm / 0.1 deg or its accepted steps become negligible. (The Gauss-Newton matrix
is what makes the ill-conditioned directions converge: plain normalised gradient ascent with the
same schedule stalls in them.) The rigid update is left-composed in atlas space:
``atlas_from_voxel <- U @ atlas_from_voxel``.

:func:`anchor_frame` removes the common rigid drift of all slices that registration cannot
constrain (the volume is built from the same slices).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from service.geometry import se3
from service.geometry.pose import make_pose
from service.geometry.sampling import FWHM_TO_SIGMA
from service.reconstruction.forward import inplane_sigma_mm, psf_quadrature
from service.reconstruction.grid import Grid, trilinear
from service.reconstruction.slices import SliceSet

MM_PER_RADIAN = 180.0 / np.pi
"""Metric of the steps: one degree of rotation weighs as much as one mm of translation."""
INITIAL_DAMPING = 1e-2
CONVERGED_STEP_MM = 0.01


@dataclass
class RegistrationResult:
    """Output of :func:`register_slices`.

    Attributes:
        atlas_from_voxel: ``[n, 4, 4]`` updated slice transforms (unchanged where not registered).
        ncc: ``[n]`` final NCC of each slice with the volume (NaN where not registered).
        registered: ``[n]`` bool, the slices that took part.
        iterations: iterations run.
    """

    atlas_from_voxel: NDArray[np.float64]
    ncc: NDArray[np.float64]
    registered: NDArray[np.bool_]
    iterations: int


class _Objective:
    """NCC of slices against a (pre-blurred) volume, with its gradient w.r.t. rigid perturbations."""

    def __init__(self, volume: NDArray, grid: Grid, slices: SliceSet, pixels: NDArray, psf_points: int,
                 blur_sigma_mm: float) -> None:
        self.volume, self.grid, self.slices, self.pixels = volume, grid, slices, pixels
        self.n = slices.n_slices
        self.sid = slices.slice_id[pixels]
        self.u, self.wq = psf_quadrature(psf_points)
        sigma_t = slices.thickness_mm * FWHM_TO_SIGMA
        self.rest = np.sqrt(np.maximum(sigma_t**2 - blur_sigma_mm**2, 0.0))
        self.count = np.bincount(self.sid, minlength=self.n).astype(np.float64)
        s = slices.values[pixels].astype(np.float64)
        mean = np.bincount(self.sid, s, self.n) / np.maximum(self.count, 1)
        self.s_c = s - mean[self.sid]
        self.s_norm = np.sqrt(np.bincount(self.sid, self.s_c**2, self.n))

    def __call__(self, poses: NDArray, which: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """NCC ``[n]``, gradient ``[n, 6]``, Gauss-Newton matrix ``[n, 6, 6]`` and centres ``[n, 3]``.

        Derivatives are w.r.t. ``(omega, t)`` of a rigid perturbation about the slice centre. Only
        slices in ``which`` are evaluated; the entries of the others are 0.
        """
        sel = which[self.sid]
        pix, sid = self.pixels[sel], self.sid[sel]
        n = self.n
        pos = self.slices.positions(poses, pix)
        cnt = np.maximum(self.count, 1.0)
        centre = np.stack([np.bincount(sid, pos[:, d], n) for d in range(3)], -1) / cnt[:, None]
        step = (self.slices.normals(poses) * self.rest[:, None])[sid]
        m = np.zeros(len(pix))
        gt = np.zeros((len(pix), 3))
        gw = np.zeros((len(pix), 3))
        rel = pos - centre[sid]
        for u, w in zip(self.u, self.wq):
            x = pos + u * step if u else pos
            val, gvox = trilinear(self.volume, self.grid.voxel_of(x), gradient=True)
            g = self.grid.gradient_to_world(gvox).astype(np.float64)
            m += w * val
            gt += w * g
            gw += w * np.cross(rel + u * step if u else rel, g)
        sc = self.s_c[sel]
        mbar = np.bincount(sid, m, n) / cnt
        mc = m - mbar[sid]
        a = np.bincount(sid, sc * m, n)
        b = np.bincount(sid, mc * mc, n)
        ok = (b > 1e-12) & (self.s_norm > 1e-12) & which
        denom = np.where(ok, self.s_norm * np.sqrt(np.where(ok, b, 1.0)), 1.0)
        ncc = np.where(ok, a / denom, 0.0)
        ratio = np.where(ok, a / np.where(ok, b, 1.0), 0.0)
        dm = np.where(ok[sid], (sc - ratio[sid] * mc) / denom[sid], 0.0)
        jac = np.concatenate([gw, gt], axis=1)                               # dm_k / d(omega, t)
        grad = np.stack([np.bincount(sid, dm * jac[:, d], n) for d in range(6)], -1)
        # Gauss-Newton matrix of 2 - 2 NCC = |s~/|s~| - m~/sqrt(B)|^2:
        # [sum J J^T - n Jbar Jbar^T - (sum J m~)(sum J m~)^T / B] / B
        jsum = np.stack([np.bincount(sid, jac[:, d], n) for d in range(6)], -1)
        jm = np.stack([np.bincount(sid, jac[:, d] * mc, n) for d in range(6)], -1)
        jj = np.zeros((n, 6, 6))
        for d in range(6):
            for e in range(d, 6):
                jj[:, d, e] = jj[:, e, d] = np.bincount(sid, jac[:, d] * jac[:, e], n)
        bb = np.where(ok, b, 1.0)[:, None, None]
        outer_mean = jsum[:, :, None] * jsum[:, None, :] / cnt[:, None, None]
        hess = (jj - outer_mean - jm[:, :, None] * jm[:, None, :] / bb) / bb
        hess[~ok] = 0.0
        return ncc, grad, hess, centre


def rigid_update(centre: NDArray, omega: NDArray, translation: NDArray) -> NDArray[np.float64]:
    """``[n, 4, 4]`` transforms ``x -> R(omega)(x - c) + c + t`` (atlas space)."""
    rot = se3.so3_exp(omega)
    c = np.asarray(centre, dtype=np.float64)
    t = c + translation - np.einsum("nij,nj->ni", rot, c)
    return make_pose(rot, t)


def _offset(poses: NDArray, prior: NDArray, centre: NDArray) -> NDArray[np.float64]:
    """``[n, 6]`` each pose's rigid offset from its prior about its centre: rotation (degrees),
    translation of the centre (mm), in the steps' metric."""
    u = poses @ np.linalg.inv(prior)
    omega = se3.so3_log(u[:, :3, :3]) * MM_PER_RADIAN
    moved = np.einsum("nij,nj->ni", u[:, :3, :3], centre) + u[:, :3, 3] - centre
    return np.concatenate([omega, moved], axis=1)


def _kabsch(p: NDArray, q: NDArray, w: NDArray) -> NDArray[np.float64]:
    """Rigid ``4 x 4`` minimising ``sum w |R p + t - q|^2`` over points ``[N, 3]``."""
    pm = (w[:, None] * p).sum(0) / w.sum()
    qm = (w[:, None] * q).sum(0) / w.sum()
    h = ((p - pm) * w[:, None]).T @ (q - qm)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return make_pose(rot, qm - rot @ pm)


def anchor_frame(slices: SliceSet, reference: ArrayLike, moved: ArrayLike, weights: NDArray | None = None,
                 reweighting: int = 3) -> NDArray[np.float64]:
    """Undo the common rigid motion of all slices between ``reference`` and ``moved`` transforms.

    Slice-to-volume registration fixes the slices relative to each other, but the whole set can
    drift rigidly from round to round (nothing ties the volume to the atlas frame). This returns
    ``G @ moved`` with ``G`` the rigid transform that best maps the pixel positions under ``moved``
    back onto those under ``reference`` (weighted least squares, Kabsch), so the frame stays the
    one of the starting (predicted) poses: their errors average out, a drift would not. The fit is
    iteratively reweighted (Cauchy weights on each slice's misfit, scale twice the median misfit),
    so that a few slices that moved far (gross errors being corrected) do not tilt the frame.

    Args:
        slices: the slice set.
        reference: ``[n, 4, 4]`` transforms defining the frame (e.g. before registration).
        moved: ``[n, 4, 4]`` registered transforms.
        weights: optional ``[n]`` slice weights (default: 1 for slices with pixels).
        reweighting: robust reweighting iterations.
    """
    moved = np.asarray(moved, dtype=np.float64)
    n = slices.n_slices
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).copy()
    counts = slices.pixel_counts()
    w[counts == 0] = 0.0
    if w.sum() <= 0:
        return moved.copy()
    p = slices.positions(moved)
    q = slices.positions(reference)
    robust = w.copy()
    g = np.eye(4)
    for _ in range(reweighting + 1):
        g = _kabsch(p, q, robust[slices.slice_id])
        misfit = np.bincount(slices.slice_id, np.linalg.norm(p @ g[:3, :3].T + g[:3, 3] - q, axis=1), n)
        misfit /= np.maximum(counts, 1)
        scale = 2.0 * float(np.median(misfit[w > 0])) + 1e-6
        robust = w / (1.0 + (misfit / scale) ** 2)
    return g @ moved


def blurred_volume(volume: NDArray, grid: Grid, blur_sigma_mm: float) -> NDArray[np.float32]:
    """``volume`` on ``grid`` blurred in-plane by ``blur_sigma_mm`` as :func:`register_slices` sees it
    (float32; unchanged for no blur)."""
    vol = np.asarray(volume, dtype=np.float32)
    return ndimage.gaussian_filter(vol, blur_sigma_mm / grid.spacing, mode="constant", truncate=3.0) \
        if blur_sigma_mm > 0 else vol


def register_slices(volume: NDArray, grid: Grid, slices: SliceSet, atlas_from_voxel: ArrayLike, *,
                    active: NDArray | None = None, subsample: int = 2, psf_points: int = 3,
                    blur_sigma_mm: float | None = None, max_iterations: int = 40, step_mm: float = 1.0,
                    min_step_mm: float = 0.1, min_pixels: int = 16,
                    max_pixels: int | None = 150_000, prior: NDArray | None = None,
                    prior_sd_mm: float | None = None, blurred: bool = False) -> RegistrationResult:
    """Rigidly register every (active) slice to ``volume`` at once.

    Args:
        volume: ``[I, J, K]`` current reconstruction on ``grid``.
        grid: its grid.
        slices: the slice set.
        atlas_from_voxel: ``[n, 4, 4]`` starting slice transforms.
        active: ``[n]`` bool, slices to register (default: all with pixels).
        subsample: use every ``subsample``-th pixel (in storage order) for speed.
        psf_points: through-plane PSF quadrature points (1: sample at the pixel centres only).
        blur_sigma_mm: isotropic in-plane PSF applied to the volume first (default: as the forward model).
        max_iterations: upper bound on iterations.
        step_mm: initial (largest) trust radius of a step (mm; 1 mm == 1 degree).
        min_step_mm: a slice stops when its trust radius falls below this.
        min_pixels: slices with fewer (subsampled) pixels are not registered.
        max_pixels: the stride is raised so that at most about this many pixels are used (the cost
            of an iteration is proportional to them; ``None``: no cap).
        prior: ``[n, 4, 4]`` transforms each slice is held near (``None``: none), with
            ``prior_sd_mm`` its expected distance (mm == degrees): the objective becomes
            ``NCC - w/2 |d|^2``, ``d`` the slice's rigid offset from its prior (about its centre) and
            ``w`` the slice's own NCC curvature in translation over ``prior_sd_mm^2``: directions the
            image constrains (translation) stay the image's, those it barely does (a thick slice's
            tilt) stay near the prior.
        blurred: ``volume`` already carries the in-plane blur (:func:`blurred_volume` with the same
            ``blur_sigma_mm``): a caller registering to one volume several times blurs it once.

    Returns:
        The :class:`RegistrationResult`.
    """
    poses = np.array(atlas_from_voxel, dtype=np.float64)
    n = slices.n_slices
    act = slices.include.copy() if active is None else np.asarray(active, bool) & slices.include
    pixels = np.flatnonzero(act[slices.slice_id])
    stride = max(int(subsample), 1, int(np.ceil(len(pixels) / max_pixels)) if max_pixels else 1)
    pixels = pixels[::stride]
    act &= np.bincount(slices.slice_id[pixels], minlength=n) >= min_pixels
    pixels = pixels[act[slices.slice_id[pixels]]]
    blur = inplane_sigma_mm(slices) if blur_sigma_mm is None else float(blur_sigma_mm)
    vol = np.asarray(volume, dtype=np.float32) if blurred else blurred_volume(volume, grid, blur)
    objective = _Objective(vol, grid, slices, pixels, psf_points, blur)
    act &= objective.s_norm > 1e-12
    ncc, grad, hess, centre = objective(poses, act)
    radius = np.where(act, float(step_mm), 0.0)
    damping = np.full(n, INITIAL_DAMPING)
    moving = act.copy()
    scale = np.array([MM_PER_RADIAN] * 3 + [1.0] * 3)        # (omega, t) -> (degrees, mm)
    held = prior is not None and bool(prior_sd_mm)
    weight = np.median(np.einsum("nii->ni", hess)[:, 3:], axis=1) / float(prior_sd_mm) ** 2 if held else np.zeros(n)

    def penalised(value: NDArray, at: NDArray, centres: NDArray) -> NDArray:
        """The objective: the NCC less the prior's penalty (the NCC itself without a prior)."""
        return value - 0.5 * weight * (_offset(at, prior, centres) ** 2).sum(1) if held else value

    score = penalised(ncc, poses, centre)
    it = 0
    for it in range(1, max_iterations + 1):
        live = moving & (radius >= min_step_mm)
        if not live.any():
            it -= 1
            break
        g = grad[live] / scale                                    # gradient w.r.t. scaled parameters
        h = hess[live] / scale[:, None] / scale[None, :]
        if held:
            g = g - weight[live, None] * _offset(poses[live], prior[live], centre[live])
            h = h + weight[live, None, None] * np.eye(6)
        diag = np.maximum(np.einsum("nii->ni", h), 1e-12)
        lhs = h + (damping[live, None] * diag)[:, :, None] * np.eye(6)
        step = np.linalg.solve(lhs, g[..., None])[..., 0]
        length = np.linalg.norm(step, axis=1)
        step *= np.minimum(1.0, radius[live] / np.maximum(length, 1e-12))[:, None]
        step /= scale
        trial = poses.copy()
        trial[live] = rigid_update(centre[live], step[:, :3], step[:, 3:]) @ poses[live]
        ncc_t, grad_t, hess_t, centre_t = objective(trial, live)
        score_t = penalised(ncc_t, trial, centre_t)
        better = live & (score_t > score)
        worse = live & ~better
        poses[better], ncc[better], score[better] = trial[better], ncc_t[better], score_t[better]
        grad[better], hess[better], centre[better] = grad_t[better], hess_t[better], centre_t[better]
        damping[better] = np.maximum(damping[better] / 3.0, 1e-6)
        damping[worse] *= 4.0
        radius[worse] *= 0.5
        done = np.zeros(n, bool)
        done[live] = np.minimum(length, radius[live]) < CONVERGED_STEP_MM
        moving &= ~(better & done)
    return RegistrationResult(poses, np.where(act, ncc, np.nan), act, it)
