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
from scipy.linalg import lapack

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
    """One block of coupled coordinates, whitened for every (kernel ``c``, error correlation ``r``),
    and reduced to tridiagonal form bordered by its observations.

    Attributes:
        coords: the coordinates it holds (indices into the six).
        b: ``[q m, q m]`` the lever operator of the voting slices (:func:`lever_operator`).
        w: ``[r, q m, q m]`` the whitener of the network's errors (block-diagonal over the coordinates).
        logdet: ``[r]`` log det of the errors' covariance.
        cov: ``[c, r, q m, q m]`` the whitened motion covariance ``W B K B^T W^T`` (plus a jitter).
        y: ``[q m]`` the observations in slice coordinates.
        diag, off: ``[c, r, q m]``, ``[c, r, q m - 1]`` the tridiagonal form ``T = Q^T cov Q`` whose
            ``Q`` takes the whitened observations ``W y`` to the first axis (:func:`bordered_tridiagonal`).
        head: ``[c, r]`` ``|W y|^2``, all of it on that first axis.
    """

    coords: tuple[int, ...]
    b: NDArray
    w: NDArray
    logdet: NDArray
    cov: NDArray
    y: NDArray
    diag: NDArray
    off: NDArray
    head: NDArray


def bordered_tridiagonal(cov: NDArray, v: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """``T = Q^T cov Q`` tridiagonal with ``Q^T v = |v| e_1``, for each matrix of ``cov [..., n, n]``
    and vector of ``v [..., n]``: the diagonal ``[..., n]``, the off-diagonal ``[..., n - 1]`` and
    ``|v|^2 [...]``.

    LAPACK's Householder reduction (``dsytrd``, lower) of the bordered matrix ``[[0, v^T], [v, cov]]``
    turns ``v`` onto the first axis with its first reflection and leaves that axis alone after it, so
    the trailing block of the result is ``T`` and its first off-diagonal entry ``|v|``. Then
    ``v^T f(cov) v = |v|^2 f(T)_11`` for any matrix function ``f``, and ``det(a cov + g I) = det(a T + g I)``:
    the likelihood of every amplitude and noise scale (:func:`nll`) needs no eigenvectors.

    Example:
        >>> rng = np.random.default_rng(0)
        >>> a = rng.normal(size=(5, 5)); cov = a @ a.T; v = rng.normal(size=5)
        >>> d, e, h = bordered_tridiagonal(cov, v)
        >>> t = np.diag(d) + np.diag(e, 1) + np.diag(e, -1)
        >>> bool(np.isclose(h * np.linalg.inv(t + np.eye(5))[0, 0], v @ np.linalg.solve(cov + np.eye(5), v)))
        True
        >>> bool(np.allclose(np.linalg.eigvalsh(t), np.linalg.eigvalsh(cov)))
        True
    """
    *lead, n = v.shape
    flat, vs = cov.reshape(-1, n, n), v.reshape(-1, n)
    diag, off, head = np.zeros((len(flat), n)), np.zeros((len(flat), max(n - 1, 0))), np.einsum("kn,kn->k", vs, vs)
    if n:
        lwork = max(int(lapack.dsytrd_lwork(n + 1)[0]), n + 1)
        border = np.zeros((n + 1, n + 1), order="F")
        for i in range(len(flat)):
            border[0, 0] = 0.0
            border[1:, 0] = vs[i]
            border[1:, 1:] = flat[i]                          # dsytrd (lower) reads the lower triangle
            _, d, e, _, info = lapack.dsytrd(border, lower=1, lwork=lwork, overwrite_a=1)
            if info:
                raise np.linalg.LinAlgError(f"dsytrd failed ({info})")
            diag[i], off[i] = d[1:], e[1:]
    return diag.reshape(*lead, n), off.reshape(*lead, max(n - 1, 0)), head.reshape(lead)


def decompose(yv: NDArray, sig: NDArray, shape: NDArray, z: NDArray, cv: NDArray, correlations: tuple[float, ...],
              neighbour_slices: float, memo: dict | None = None) -> list[Block]:
    """The blocks of the voting slices' coordinates ``yv [m, 6]`` (stack frame), their errors
    ``sig * sqrt(shape[:, d])`` in slice coordinates, offsets ``z [m]`` and motion correlations ``cv [c, m, m]``.

    The whitened covariances depend on everything but ``yv``: with ``memo`` (a dict the caller keeps),
    a second call with the same errors, offsets and correlations (a stack's final fit, whose votes
    and branches the earlier fit left as they were, or chose on the same votes) reuses them and only
    reduces them with its own ``yv``.
    """
    key = None if memo is None else (np.asarray(sig, np.float64).tobytes(), np.asarray(shape, np.float64).tobytes(),
                                     np.asarray(z, np.float64).tobytes(), np.asarray(cv, np.float64).tobytes(),
                                     tuple(correlations), neighbour_slices)
    if memo is not None and key in memo:
        return [_project(bl, yv) for bl in memo[key]]
    blocks = _whiten(sig, shape, z, cv, correlations, neighbour_slices)
    if memo is not None:
        memo[key] = blocks
    return [_project(bl, yv) for bl in blocks]


def _project(bl: Block, yv: NDArray) -> Block:
    """``bl`` (its whitened covariances) with the observations ``yv [m, 6]`` and their tridiagonal forms."""
    y = bl.b @ yv[:, list(bl.coords)].T.reshape(-1)
    v = np.broadcast_to(bl.w @ y, (*bl.cov.shape[:2], len(y)))                              # [c, r, qm]
    return Block(bl.coords, bl.b, bl.w, bl.logdet, bl.cov, y, *bordered_tridiagonal(bl.cov, v))


def _whiten(sig: NDArray, shape: NDArray, z: NDArray, cv: NDArray, correlations: tuple[float, ...],
            neighbour_slices: float) -> list[Block]:
    """The blocks' whiteners and whitened motion covariances (no observations yet)."""
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
        cov = wb[None] @ prior[:, None] @ np.swapaxes(wb, 1, 2)[None] + JITTER * np.eye(q * m)
        out.append(Block(coords, b, w, logdet, cov, np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0)))
    return out


def nll(blocks: list[Block], amps: NDArray, scales: NDArray) -> NDArray[np.float64]:
    """``[c, r, a, g]`` negative log marginal likelihood of every kernel, error correlation,
    amplitude (``amps``: a^2) and noise scale (``scales``: g^2): the whitened covariance is
    ``M = a^2 cov + g^2 I``, and on the tridiagonal form (:func:`bordered_tridiagonal`) the pivots
    ``p_i = M_ii - M_i,i+1^2 / p_i+1`` of its factorisation from the last row up give both
    ``log det M = sum log p_i`` and ``(W y)^T M^-1 (W y) = |W y|^2 / p_1``, every model at once."""
    total = 0.0
    a2, g2 = np.asarray(amps, np.float64)[:, None], np.asarray(scales, np.float64)[None, :]
    for bl in blocks:
        n = bl.diag.shape[-1]
        logdet = 0.5 * bl.logdet[None, :, None, None]
        if not n:
            total = total + logdet
            continue
        pivot = a2 * bl.diag[..., n - 1, None, None] + g2                                  # [c, r, a, g]
        log_m = np.log(pivot)
        for i in range(n - 2, -1, -1):
            pivot = a2 * bl.diag[..., i, None, None] + g2 - (a2 * bl.off[..., i, None, None]) ** 2 / pivot
            log_m += np.log(pivot)
        total = total + 0.5 * bl.head[..., None, None] / pivot + 0.5 * log_m + logdet
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
        wr = bl.w[r]                                                                        # [k, qm, qm]
        c_inv = np.swapaxes(wr, 1, 2) @ np.linalg.solve(amp2[:, None, None] * bl.cov[c, r]
                                                        + g2[:, None, None] * np.eye(q * m), wr)
        c_inv = 0.5 * (c_inv + np.swapaxes(c_inv, 1, 2))                                   # [k, qm, qm]
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
