"""Intensity matching: each slice's gain and in-plane shading, fitted against the volume simulated at its pose.

A slice's intensities differ from its neighbours' by more than its anatomy: the coil's sensitivity
(a bias field) changes across the field of view and, as the fetus moves, over the brain from slice
to slice; single-shot sequences add a gain per slice. One scale per stack (what
:meth:`~service.reconstruction.slices.SliceSet.from_stacks` applies) leaves all of it in the data,
and the super-resolution volume takes it for anatomy. As SVRTK does (Kuklisova-Murgasova et al.
2012, a scale and a bias field per slice), each SVR round fits every slice's multiplicative
correction

    g(u, v) = a + b u + c v

(``u``, ``v`` the pixel's in-plane position about the slice's centre, in units of the slice's RMS
radius: ``b`` and ``c`` are the shading's share one RMS radius from the centre) by weighted least
squares of the slice's corrected pixels ``g s`` onto the volume simulated at its pose, the robust
inlier weights weighting the pixels; a prior worth a few typical pixels pulls each fit towards no
correction (:data:`GAIN_PRIOR_PIXELS`, :data:`SHADING_PRIOR_PIXELS`), so a slice of few pixels
keeps about its own intensities and a full one hardly feels it. The corrections are divided by
their median gain over the fitted slices: they match slices to each other, not the volume's
overall brightness, which therefore cannot drift over the rounds. The corrected values serve the
robust weights, the super-resolution, the later rounds' registration (NCC: the gain does not
matter to it, the shading does) and each slice's agreement with the final volume; the
leave-one-stack-out score judges each slice as acquired (:mod:`~service.reconstruction.quality`).

Example (a slice at 0.8 of the volume's brightness, shaded 20 % from side to side):
    >>> import numpy as np
    >>> from service.io.volume import Volume
    >>> from service.reconstruction.slices import SliceSet
    >>> vol = Volume(np.ones((16, 16, 1), np.float32), np.eye(4))
    >>> ss = SliceSet.from_stacks([(vol, None, vol.affine[None], [True])])
    >>> u = ss.voxel[:, 0] - 7.5
    >>> observed = ss.values * 0.8 * (1 + 0.2 * u / 7.5)
    >>> gains = fit_intensity(ss, ss.values, observed, np.ones(len(u)), np.array([True]), normalise=False)
    >>> corrected = observed * gains.factor(ss)
    >>> [round(float(np.abs(x / ss.values - 1).mean()), 2) for x in (observed, corrected)]
    [0.2, 0.02]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.reconstruction.slices import SliceSet

MIN_PIXELS = 50
"""A slice with fewer weighted pixels keeps no correction: its fit would say little."""
GAIN_PRIOR_PIXELS = 5.0
"""The pull of a slice's gain towards 1, worth this many typical pixels: a slice of a few dozen
pixels stays near its own intensities, a full one hardly feels it."""
SHADING_PRIOR_PIXELS = 25.0
"""The pull of each shading term towards none, worth this many typical pixels (a shading term's
pixels weigh about half a gain's: shading needs more pixels to show)."""
GAIN_RANGE = (0.5, 2.0)
"""A slice's gain relative to the typical slice's stays within this range (a gain beyond it is a
slice at a wrong pose, not a coil)."""
MAX_SHADING = 0.3
"""Each shading term stays within this share of the gain (about +-60 % across a slice's brain)."""


@dataclass
class SliceIntensity:
    """Per-slice multiplicative corrections ``a + b u + c v`` (:func:`fit_intensity`).

    Attributes:
        gain: ``[n]`` the correction at the slice's centre (1: none).
        shading: ``[n, 2]`` its change per RMS radius along the slice's two in-plane voxel axes.
        centre: ``[n, 2]`` the slice's centre in those axes (mm), its pixels weighted as the fit
            weighs them (weight x intensity squared).
        radius: ``[n]`` its pixels' RMS distance from that centre, weighted alike (mm).
        fitted: ``[n]`` the slices fitted (the others at no correction).
    """

    gain: NDArray[np.float64]
    shading: NDArray[np.float64]
    centre: NDArray[np.float64]
    radius: NDArray[np.float64]
    fitted: NDArray[np.bool_]

    @classmethod
    def none(cls, n: int) -> "SliceIntensity":
        """No correction for ``n`` slices."""
        return cls(np.ones(n), np.zeros((n, 2)), np.zeros((n, 2)), np.ones(n), np.zeros(n, bool))

    def factor(self, slices: SliceSet) -> NDArray[np.float32]:
        """``[N]`` each pixel's correction: its corrected intensity is ``slices.values * factor``."""
        u, v = _unit_coordinates(slices, self.centre, self.radius)
        sid = slices.slice_id
        g = self.gain[sid] + self.shading[sid, 0] * u + self.shading[sid, 1] * v
        return np.clip(g, 0.25 * self.gain[sid], 4.0 * self.gain[sid]).astype(np.float32)

    def summary(self, which: NDArray[np.bool_]) -> dict:
        """The corrections of the fitted slices among ``which`` in a report: how many, the 5th-95th
        percentile of their gains and their largest shading (the two terms' combined size, a
        share of the gain at one RMS radius).

        Example:
            >>> c = SliceIntensity.none(3)
            >>> c.gain[:] = [0.9, 1.0, 1.2]; c.shading[2] = [0.03, 0.04]; c.fitted[:] = True
            >>> c.summary(np.array([True, True, True]))
            {'slices': 3, 'gain_p5_p95': [0.91, 1.18], 'max_shading': 0.042}
        """
        which = np.asarray(which, bool) & self.fitted
        if not which.any():
            return {"slices": 0, "gain_p5_p95": [1.0, 1.0], "max_shading": 0.0}
        gain = self.gain[which]
        shading = np.hypot(*self.shading[which].T) / gain
        return {"slices": int(which.sum()), "gain_p5_p95": [round(float(np.percentile(gain, q)), 3) for q in (5, 95)],
                "max_shading": round(float(shading.max()), 3)}


def in_plane_mm(slices: SliceSet) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``[N]`` each pixel's position (mm) along its slice's first and second in-plane voxel axes.

    Example (slices along the first voxel axis: their pixels lie along the second and third):
        >>> from service.io.volume import Volume
        >>> vol = Volume(np.ones((2, 3, 4), np.float32), np.diag([3.0, 1.5, 2.0, 1.0]))
        >>> ss = SliceSet.from_stacks([(vol, None, np.repeat(vol.affine[None], 2, 0), [True, True])])
        >>> u, v = in_plane_mm(ss)
        >>> float(u.max()), float(v.max())
        (3.0, 6.0)
    """
    sid = slices.slice_id
    spacing = np.linalg.norm(slices.stack_affine[:, :3, :3], axis=1)          # [n, 3] column norms
    axis = slices.slice_axis
    first = np.where(axis == 0, 1, 0)
    second = np.where(axis == 2, 1, 2)
    rows = np.arange(len(sid))
    vox = slices.voxel.astype(np.float64)
    u = vox[rows, first[sid]] * spacing[sid, first[sid]]
    v = vox[rows, second[sid]] * spacing[sid, second[sid]]
    return u, v


def _unit_coordinates(slices: SliceSet, centre: NDArray, radius: NDArray) -> tuple[NDArray, NDArray]:
    u, v = in_plane_mm(slices)
    sid = slices.slice_id
    return (u - centre[sid, 0]) / radius[sid], (v - centre[sid, 1]) / radius[sid]


def fit_intensity(slices: SliceSet, simulated: NDArray, observed: NDArray, weight: NDArray,
                  fitted: NDArray[np.bool_], *, shading: bool = True, normalise: bool = True) -> SliceIntensity:
    """Each slice's correction of ``observed`` (``[N]``, its pixels' intensities) onto ``simulated``
    (the volume through the acquisition model at the slice's pose), by weighted least squares.

    Args:
        slices: the slices (their geometry; their values are not read).
        simulated: ``[N]`` the volume simulated at each pixel.
        observed: ``[N]`` the pixels' intensities as acquired.
        weight: ``[N]`` each pixel's weight (the robust inlier probabilities).
        fitted: ``[n]`` the slices to fit (the others keep no correction).
        shading: also fit the in-plane shading (else the gain alone).
        normalise: divide the fitted corrections by their median gain (the other slices, at no
            correction, then sit at the typical slice's).

    Returns:
        The :class:`SliceIntensity`.
    """
    n, sid = slices.n_slices, slices.slice_id
    out = SliceIntensity.none(n)
    if slices.n_pixels == 0:
        return out
    s = np.asarray(observed, np.float64)
    m = np.asarray(simulated, np.float64)
    finite = np.isfinite(s) & np.isfinite(m)
    w = np.where(finite, np.clip(np.nan_to_num(np.asarray(weight, np.float64)), 0.0, None), 0.0)
    s, m = np.where(finite, s, 0.0), np.where(finite, m, 0.0)
    ws = w * s * s                    # the normal equations' weights: about this centre the terms decouple
    u_mm, v_mm = in_plane_mm(slices)
    safe = np.maximum(np.bincount(sid, ws, n), 1e-12)
    centre = np.stack([np.bincount(sid, ws * u_mm, n), np.bincount(sid, ws * v_mm, n)], -1) / safe[:, None]
    du, dv = u_mm - centre[sid, 0], v_mm - centre[sid, 1]
    radius = np.sqrt(np.bincount(sid, ws * (du**2 + dv**2), n) / safe)
    out.centre, out.radius = centre, np.where(radius > 1e-6, radius, 1.0)
    phi = [s, s * du / out.radius[sid], s * dv / out.radius[sid]] if shading else [s]
    k = len(phi)
    normal = np.empty((n, k, k))
    for i in range(k):
        for j in range(i, k):
            normal[:, i, j] = normal[:, j, i] = np.bincount(sid, w * phi[i] * phi[j], n)
    target = np.stack([np.bincount(sid, w * p * m, n) for p in phi], -1)
    counted = np.bincount(sid, (w > 0).astype(np.float64), n)
    ok = np.asarray(fitted, bool) & (counted >= MIN_PIXELS) & (normal[:, 0, 0] > 1e-12)
    if not ok.any():
        return out
    typical_pixel = float(np.median(ws[(w > 0) & ok[sid]]))
    ridge = typical_pixel * np.array([GAIN_PRIOR_PIXELS] + [SHADING_PRIOR_PIXELS] * (k - 1))
    normal[:, range(k), range(k)] += ridge
    target[:, 0] += ridge[0]                                            # the prior: gain 1, no shading
    theta = np.linalg.solve(normal[ok], target[ok][..., None])[..., 0]
    if normalise:                       # relative to the typical slice first, then bounded
        theta /= float(np.median(theta[:, 0]))
    gain = np.clip(theta[:, 0], *GAIN_RANGE)
    out.gain[ok] = gain
    if shading:
        out.shading[ok] = np.clip(theta[:, 1:], -MAX_SHADING * gain[:, None], MAX_SHADING * gain[:, None])
    out.fitted = ok
    return out
