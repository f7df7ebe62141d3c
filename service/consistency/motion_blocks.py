"""The linear algebra of the motion model: a stack's six coordinates in blocks that a slice's lever arm couples.

The motion model (:mod:`service.consistency.motion_model`) follows each slice's proposal of the
stack's ``atlas_from_scanner`` in six coordinates about the stack's centre: the rotation vector
(mm at the anchor radius) and the translation of the centre, along the stack's axes (x, y in the
plane, the normal). The network errs in the *slice's* own coordinates, about the slice's origin,
which lies ``z`` mm along the normal from the centre. A tilt error ``w`` there moves the implied
centre by ``w x (-z n)``, so in the stack's coordinates a slice's tilt and in-plane translation
errors are one error seen twice: rotation about x with translation along y, rotation about y
with translation along x. Treating them as independent (only their variances) throws away what
makes the slices of one stack agree on its tilt: their in-plane positions at different depths.

So the model works in the slices' coordinates: ``y~_k = B_k y_k``, with ``B_k`` the identity but for
``t_x += (z_k / R) r_y`` and ``t_y -= (z_k / R) r_x`` (``R`` the anchor radius, the unit of the
rotation coordinates), where the errors are independent per coordinate. The motion, smooth in
the stack's coordinates, is seen through ``B``: the coordinates form the blocks
``(r_x, t_y)``, ``(r_y, t_x)``, ``(r_z)``, ``(t_z)``, each a Gaussian process of its own. With every
slice at the centre (``z = 0``) ``B`` is the identity and the blocks fall apart into the six
coordinates of the uncoupled model.

Example (two slices 30 mm either side of the centre, rotation about x by 0.1 rad in mm at 60 mm):
    >>> import numpy as np
    >>> b = lever_operator((0, 4), np.array([-0.5, 0.5]))
    >>> (b @ np.array([6.0, 6.0, 0.0, 0.0])).round(2).tolist()    # (r_x, r_x, t_y, t_y) -> slices
    [6.0, 6.0, 3.0, -3.0]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

BLOCKS: tuple[tuple[int, ...], ...] = ((0, 4), (1, 3), (2,), (5,))
"""The coordinates (r_x, r_y, r_z, t_x, t_y, t_z) a slice's offset along the normal couples."""
LEVER_SIGN = {(0, 4): -1.0, (1, 3): 1.0}
"""``t_slice = t_centre + sign * z / R * r`` in each coupled block."""
JITTER = 1e-6


def lever_operator(block: tuple[int, ...], z: NDArray) -> NDArray[np.float64]:
    """``[q m, q m]``: slice coordinates from the stack's of ``m`` slices at offsets ``z`` (along the
    normal, in anchor radii), coordinate-major (all slices' first coordinate, then the second)."""
    m = len(z)
    b = np.eye(len(block) * m)
    sign = LEVER_SIGN.get(block)
    if sign is not None:
        b[m:, :m] = sign * np.diag(z)
    return b


def block_diagonal(x: NDArray, q: int) -> NDArray[np.float64]:
    """``q`` copies of ``x [..., a, b]`` on the diagonal of a ``[..., q a, q b]`` matrix (``kron(eye(q), x)``
    of each matrix of a batch, without its outer product).

    Example:
        >>> block_diagonal(np.array([[1.0, 2.0]]), 2).tolist()
        [[1.0, 2.0, 0.0, 0.0], [0.0, 0.0, 1.0, 2.0]]
    """
    if q == 1:
        return np.asarray(x, dtype=np.float64)
    *lead, a, b = x.shape
    out = np.zeros((*lead, q * a, q * b))
    for i in range(q):
        out[..., i * a:(i + 1) * a, i * b:(i + 1) * b] = x
    return out


def whiteners(sig: NDArray, correlations: tuple[float, ...], neighbour_slices: float) -> tuple[NDArray, NDArray]:
    """Per error correlation ``r``: ``W_r`` with ``W_r E_r W_r^T = I``, ``E_r = R_r * s s^T / 3`` the
    network's errors of one coordinate (``R_r``: correlation ``r`` between neighbours in space, decaying
    over ``neighbour_slices``), and ``log det E_r``; ``[r, m, m]`` and ``[r]``."""
    k = np.arange(len(sig), dtype=np.float64)
    near = np.exp(-0.5 * ((k[:, None] - k[None]) / neighbour_slices) ** 2)
    rho = np.asarray(correlations)[:, None, None]
    lam, q = np.linalg.eigh(rho * near + (1.0 - rho) * np.eye(len(sig)))                   # [r, m], [r, m, m]
    d = sig / np.sqrt(3.0)
    w = (q / np.sqrt(lam)[:, None]) @ np.swapaxes(q, 1, 2) / d[None, None, :]              # R^-1/2 D^-1
    return w, np.log(lam).sum(-1) + 2.0 * np.log(d).sum()


@dataclass
class Block:
    """One block of coupled coordinates, whitened and decomposed for every (kernel ``c``, error correlation ``r``).

    Attributes:
        coords: the coordinates it holds (indices into the six).
        b: ``[q m, q m]`` the lever operator of the voting slices (:func:`lever_operator`).
        w: ``[r, q m, q m]`` the whitener of the network's errors (block-diagonal over the coordinates).
        logdet: ``[r]`` log det of the errors' covariance.
        lam, u: ``[c, r, q m]``, ``[c, r, q m, q m]`` eigendecomposition of the whitened motion covariance.
        y: ``[q m]`` the observations in slice coordinates.
        yt: ``[c, r, q m]`` the observations whitened and rotated to the eigenvectors.
    """

    coords: tuple[int, ...]
    b: NDArray
    w: NDArray
    logdet: NDArray
    lam: NDArray
    u: NDArray
    y: NDArray
    yt: NDArray


def decompose(yv: NDArray, sig: NDArray, shape: NDArray, z: NDArray, cv: NDArray, correlations: tuple[float, ...],
              neighbour_slices: float, memo: dict | None = None) -> list[Block]:
    """The blocks of the voting slices' coordinates ``yv [m, 6]`` (stack frame), their errors
    ``sig * sqrt(shape[:, d])`` in slice coordinates, offsets ``z [m]`` and motion correlations ``cv [c, m, m]``.

    The eigendecompositions depend on everything but ``yv``: with ``memo`` (a dict the caller keeps),
    a second call with the same errors, offsets and correlations (a stack's final fit, whose votes
    and branches the earlier fit left as they were, or chose on the same votes) reuses them and only
    projects its own ``yv``.
    """
    key = None if memo is None else (np.asarray(sig, np.float64).tobytes(), np.asarray(shape, np.float64).tobytes(),
                                     np.asarray(z, np.float64).tobytes(), np.asarray(cv, np.float64).tobytes(),
                                     tuple(correlations), neighbour_slices)
    if memo is not None and key in memo:
        return [_project(bl, yv) for bl in memo[key]]
    blocks = _factorise(yv, sig, shape, z, cv, correlations, neighbour_slices)
    if memo is not None:
        memo[key] = blocks
    return blocks


def _project(bl: Block, yv: NDArray) -> Block:
    """``bl`` (its factorisation) with the observations ``yv [m, 6]`` instead of its own."""
    y = bl.b @ yv[:, list(bl.coords)].T.reshape(-1)
    yt = (np.swapaxes(bl.u, -1, -2) @ (bl.w @ y)[None, :, :, None])[..., 0]
    return Block(bl.coords, bl.b, bl.w, bl.logdet, bl.lam, bl.u, y, yt)


def _factorise(yv: NDArray, sig: NDArray, shape: NDArray, z: NDArray, cv: NDArray, correlations: tuple[float, ...],
               neighbour_slices: float) -> list[Block]:
    """:func:`decompose` without a memo."""
    m = len(sig)
    cache: dict[bytes, tuple[NDArray, NDArray]] = {}
    out = []
    for coords in BLOCKS:
        q = len(coords)
        b = lever_operator(coords, z)
        w = np.zeros((len(correlations), q * m, q * m))
        logdet = np.zeros(len(correlations))
        for i, d in enumerate(coords):
            key = shape[:, d].tobytes()
            if key not in cache:
                cache[key] = whiteners(sig * np.sqrt(shape[:, d]), correlations, neighbour_slices)
            wd, ld = cache[key]
            w[:, i * m:(i + 1) * m, i * m:(i + 1) * m] = wd
            logdet += ld
        prior = np.zeros((len(cv), q * m, q * m))
        for i in range(q):
            prior[:, i * m:(i + 1) * m, i * m:(i + 1) * m] = cv
        wb = w @ b                                                                          # [r, qm, qm]
        lam, u = np.linalg.eigh(wb[None] @ prior[:, None] @ np.swapaxes(wb, 1, 2)[None] + JITTER * np.eye(q * m))
        out.append(_project(Block(coords, b, w, logdet, np.maximum(lam, 0.0), u, np.zeros(0), np.zeros(0)), yv))
    return out


def nll(blocks: list[Block], amps: NDArray, scales: NDArray) -> NDArray[np.float64]:
    """``[c, r, a, g]`` negative log marginal likelihood of every kernel, error correlation,
    amplitude (``amps``: a^2) and noise scale (``scales``: g^2); the whitened covariance's
    eigenvalues are ``a^2 lam + g^2``."""
    total = 0.0
    for bl in blocks:
        ev = amps[:, None, None] * bl.lam[:, :, None, None] + scales[:, None]               # [c, r, a, g, qm]
        total = total + (0.5 * np.einsum("crm,cragm->crag", bl.yt ** 2, 1.0 / ev) + 0.5 * np.log(ev).sum(-1)
                         + 0.5 * bl.logdet[None, :, None, None])
    return total


@dataclass
class Posterior:
    """The posteriors of ``k`` models over all ``n`` slices (stack coordinates unless said).

    Attributes:
        mean: ``[k, n, 6]`` the motion at each slice.
        cov: ``[k, 6, n, n]`` its covariance per coordinate (the rigid fit's uncertainty included).
        slice_var: ``[k, n, 6]`` its variance in each slice's own coordinates.
        loo: ``[k, m, 6]`` what the other voting slices predict for each voting slice.
        loo_var: ``[k, m, 6]`` that prediction's variance in slice coordinates (less the slice's own error).
    """

    mean: NDArray
    cov: NDArray
    slice_var: NDArray
    loo: NDArray
    loo_var: NDArray


def posterior(blocks: list[Block], c: NDArray, r: NDArray, amp2: NDArray, g2: NDArray, k_all: NDArray,
              k_nn: NDArray, z_all: NDArray, z_vote: NDArray, noise_var: NDArray) -> Posterior:
    """The posteriors of ``k`` models at once: model ``i`` has kernel ``c[i]`` (``k_all[i] [n, m]``,
    ``k_nn[i] [n, n]`` its correlations), error correlation ``r[i]``, amplitude ``amp2[i]`` (a^2) and
    noise scale ``g2[i]`` (g^2); ``noise_var [m, 6]`` the voting slices' error variances per
    coordinate (before ``g2``). Universal kriging: the rigid fit the coordinates are taken at is an
    estimate too (its GLS variance is added). One batched product per step serves every model of
    the grid's average (the matrices are small: the work is the calls).

    Example (one model, two voting slices, every coordinate its own block):
        >>> rng = np.random.default_rng(0)
        >>> sig, z, kern = np.ones(2), np.zeros(2), np.exp(-0.5 * np.subtract.outer(np.arange(2.0), np.arange(2.0)) ** 2)
        >>> bl = decompose(rng.normal(size=(2, 6)), sig, np.ones((2, 6)), z, kern[None], (0.0,), 1.5)
        >>> p = posterior(bl, np.array([0]), np.array([0]), np.array([4.0]), np.array([1.0]), kern[None], kern[None], z, z, np.ones((2, 6)) / 3)
        >>> p.mean.shape, p.cov.shape, p.loo.shape
        ((1, 2, 6), (1, 6, 2, 2), (1, 2, 6))
    """
    c, r = np.asarray(c, np.intp), np.asarray(r, np.intp)
    amp2, g2 = np.asarray(amp2, np.float64), np.asarray(g2, np.float64)
    k, (n, m) = len(c), k_all.shape[1:]
    mean, cov = np.zeros((k, n, 6)), np.zeros((k, 6, n, n))
    slice_var, loo, loo_var = np.zeros((k, n, 6)), np.zeros((k, m, 6)), np.zeros((k, m, 6))
    kern_all, kern_nn = amp2[:, None, None] * k_all, amp2[:, None, None] * k_nn
    for bl in blocks:
        q = len(bl.coords)
        ev = amp2[:, None] * bl.lam[c, r] + g2[:, None]                                    # [k, qm]
        wu = np.swapaxes(bl.w[r], 1, 2) @ bl.u[c, r]                                        # [k, qm, qm]
        c_inv = (wu / ev[:, None, :]) @ np.swapaxes(wu, 1, 2)
        alpha = (c_inv @ bl.y[:, None])[..., 0]                                             # [k, qm]
        k_star = block_diagonal(kern_all, q) @ bl.b.T                                       # cov(f, y~) [k, qn, qm]
        f = (k_star @ alpha[..., None])[..., 0]
        h = bl.b @ block_diagonal(np.ones((m, 1)), q)                                       # the offset, seen [qm, q]
        hc = h.T @ c_inv                                                                    # [k, q, qm]
        gls = hc @ h
        k_star_t = np.swapaxes(k_star, 1, 2)
        rem = block_diagonal(np.ones((1, n)), q) - hc @ k_star_t                            # [k, q, qn]
        full = (block_diagonal(kern_nn, q) - k_star @ (c_inv @ k_star_t)
                + np.swapaxes(rem, 1, 2) @ np.linalg.solve(gls + 1e-12 * np.eye(q), rem))   # [k, qn, qn]
        sub = np.moveaxis(np.diagonal(c_inv.reshape(k, q, m, q, m), axis1=2, axis2=4), -1, 1)   # [k, m, q, q]
        sub_inv = np.linalg.inv(sub)
        y_loo = bl.y.reshape(q, m).T - (sub_inv @ np.swapaxes(alpha.reshape(k, q, m), 1, 2)[..., None])[..., 0]
        var_n = np.swapaxes(np.diagonal(full, axis1=1, axis2=2).reshape(k, q, n), 1, 2)    # [k, n, q]
        sub_var = np.diagonal(sub_inv, axis1=2, axis2=3)                                    # [k, m, q]
        for i, d in enumerate(bl.coords):
            mean[:, :, d] = f[:, i * n:(i + 1) * n]
            cov[:, d] = full[:, i * n:(i + 1) * n, i * n:(i + 1) * n]
            slice_var[:, :, d] = var_n[:, :, i]
            loo_var[:, :, d] = sub_var[:, :, i] - g2[:, None] * noise_var[:, d]
            loo[:, :, d] = y_loo[:, :, i]
        sign = LEVER_SIGN.get(bl.coords)
        if sign is not None:                      # the translation seen at the slice: t + s z r
            rot, tra = bl.coords
            cross = np.diagonal(full[:, n:, :n], axis1=1, axis2=2)                          # [k, n]
            slice_var[:, :, tra] += z_all ** 2 * var_n[:, :, 0] + 2.0 * sign * z_all * cross
            loo[:, :, tra] -= sign * z_vote * loo[:, :, rot]                                # back to the stack's
    return Posterior(mean, cov, slice_var, loo, loo_var)


def to_slices(v: NDArray, z: NDArray) -> NDArray[np.float64]:
    """``[..., n, 6]`` stack-frame coordinates seen in the slices' own (``t += s z r`` per coupled block)."""
    out = np.array(v, dtype=np.float64, copy=True)
    for (rot, tra), sign in LEVER_SIGN.items():
        out[..., tra] += sign * z * v[..., rot]
    return out
