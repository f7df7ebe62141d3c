"""The derivatives of the image term by each slice's pose, and the normal equations they give.

:func:`image_jacobian` differentiates the residuals of :class:`~service.consistency.intersections.ImageTerm`
(two slices' intensities at points of their intersection line) by a right perturbation of each
slice's pose in its network frame; :class:`PointJacobian` holds them as two 6-vectors per point and
assembles ``J^T W J`` and ``J^T W r`` pair by pair for the Levenberg-Marquardt steps of
:func:`~service.consistency.image_refinement.refine`.

Example (one point of one pair, slices 1 and 0 of two free slices):
    >>> import numpy as np
    >>> jac = PointJacobian(np.ones((1, 2, 6)), np.array([[1, 0]]), np.array([0]), np.array([0]), 12)
    >>> hess, grad = jac.normal(np.array([1.0]), np.array([2.0]))
    >>> hess.shape, grad.tolist()
    ((12, 12), [2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from service.consistency.intersections import ImageTerm, lines
from service.core.threads import two_threads
from service.geometry import se3


@dataclass
class PointJacobian:
    """The image residuals' derivatives, two blocks per point: by the twist of each of the point's
    pair's two slices (``values [P, 2, 6]``), in the columns ``6 c + (0..5)`` of the pair's slices'
    free columns ``c = pair_cols[pair_of]`` (``pair_cols [M, 2]``; -1: a slice that keeps its pose).
    Every residual depends on two slices only, so the normal equations are assembled pair by pair
    (:meth:`normal`), with no sparse matrix."""

    values: NDArray[np.float64]
    pair_cols: NDArray[np.int64]          # [M, 2] each pair's slices' free columns
    pair_of: NDArray[np.int64]            # [P] each point's pair
    place: NDArray[np.int64]              # [P] its place along the pair's line (unique within a pair)
    n_params: int

    def sparse(self) -> sparse.csr_matrix:
        """``[P, n_params]`` the same derivatives as a sparse matrix."""
        cols = self.pair_cols[self.pair_of]                                   # [P, 2]
        ok = cols >= 0
        rows = np.repeat(np.nonzero(ok)[0], 6)
        return sparse.csr_matrix((self.values[ok].ravel(), (rows, (6 * cols[ok][:, None] + np.arange(6)).ravel())),
                                 shape=(len(self.values), self.n_params))

    def normal(self, weights: NDArray, r: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``J^T W J`` (dense, ``[n_params, n_params]``) and ``J^T W r`` for point weights ``weights [P]``.

        The points of one pair share its two slices: each pair's ``12 x 12`` block is one small
        matrix product over its points (all pairs in one batched product, each line's points at
        their places), then added into the four ``6 x 6`` blocks of its two slices.

        Example:
            >>> v = np.arange(12.0).reshape(1, 2, 6) / 10
            >>> jac = PointJacobian(v, np.array([[1, 0]]), np.array([0]), np.array([0]), 12)
            >>> h, g = jac.normal(np.array([2.0]), np.array([0.5]))
            >>> dense = jac.sparse().toarray()
            >>> bool(np.allclose(h, 2.0 * dense.T @ dense)), bool(np.allclose(g, dense[0]))
            (True, True)
        """
        n, count, pairs = self.n_params, len(self.values), len(self.pair_cols)
        if not count:
            return np.zeros((n, n)), np.zeros(n)
        v = np.where((self.pair_cols[self.pair_of] >= 0)[..., None], self.values, 0.0).reshape(count, 12)
        lined = np.zeros((pairs, int(self.place.max()) + 1, 12))
        lined[self.pair_of, self.place] = v
        weighed = np.zeros_like(lined)
        weighed[self.pair_of, self.place] = v * weights[:, None]
        blocks = np.swapaxes(weighed, 1, 2) @ lined                               # [M, 12, 12]
        index = (6 * np.maximum(self.pair_cols, 0)[:, :, None] + np.arange(6)).reshape(pairs, 12)
        hess = np.bincount((index[:, :, None] * n + index[:, None, :]).ravel(), blocks.ravel(), n * n).reshape(n, n)
        grad = np.bincount(index[self.pair_of].ravel(), (v * (weights * r)[:, None]).ravel(), n)
        return hess, grad


def image_jacobian(term: ImageTerm, atlas_from_slice: NDArray, poses: NDArray, col: NDArray,
                   noise: float) -> PointJacobian:
    """The image residuals' derivatives by each free slice's twist (its network frame), two blocks
    per point (:class:`PointJacobian`).

    A slice moved by a small rigid motion ``(w, v)`` of the atlas moves the pair's line with it: its
    plane ``n . x = c`` turns (``dn = w x n``, ``dc = n . v``), the line's direction
    ``d = n_a x n_b / |n_a x n_b|`` turns, and the point of the line nearest the two slices' mean
    origin moves (``L dp = rhs``, ``L`` the rows ``n_a, n_b, d``). A point ``x = p + t d`` moves by
    ``dx``; the moved slice sees it at ``dx - (w x x + v)`` in its own frame, the other at ``dx``.
    So for ``r = I_a - I_b`` with gradients ``G_a``, ``G_b`` (atlas mm):
    ``dr = (G_a - G_b) . dx - G_a . (w x x + v)`` when ``a`` moves, ``... + G_b . (w x x + v)`` when
    ``b`` does; ``(w, v)`` is ``Ad(P) d`` of the twist ``d`` in the network frame of the slice's
    current pose ``P`` (``w = R d_w``, ``v = R d_v + t x w``). Checked against finite differences
    in the tests."""
    grad = term.gradients(atlas_from_slice)
    pairs, j, tt = term.pairs, term.pair_of, term.t[term.t_of]
    ln = lines(atlas_from_slice, atlas_from_slice, pairs)
    na, nb, oa, ob, d, m, p = ln.na, ln.nb, ln.oa, ln.ob, ln.d, ln.m, ln.p
    inv = np.linalg.inv(ln.lhs)                                            # columns: dp per unit of each rhs
    perp = (np.eye(3) - d[:, :, None] * d[:, None, :]) / ln.size[:, None, None]
    differ = grad[0] - grad[1]
    values = np.zeros((len(j), 2, 6))

    def derive(role: int) -> None:
        n, o = (na, oa) if role == 0 else (nb, ob)
        dd = perp @ se3.hat(nb) @ se3.hat(na) if role == 0 else -perp @ se3.hat(na) @ se3.hat(nb)        # d(d)/dw
        q = np.einsum("mji,mj->mi", dd, m - p)
        c_own, c_line = inv[:, :, role], inv[:, :, 2]
        dp_w = -c_own[:, :, None] * np.cross(n, p)[:, None, :] + c_line[:, :, None] * (q + 0.5 * np.cross(o, d))[:, None, :]
        dp_v = c_own[:, :, None] * n[:, None, :] + 0.5 * c_line[:, :, None] * d[:, None, :]
        g = pairs[:, role]
        rot_t, shift = np.swapaxes(poses[g, :3, :3], 1, 2), poses[g, :3, 3]
        # per pair, in the slice's network frame: dr = K1 G + t K2 G (rotation), K3 G (shift), G = G_a - G_b,
        # plus the slice's own image seen moving: -+ (x - shift) x G_own and -+ G_own
        k = np.concatenate([rot_t @ (np.swapaxes(dp_w, 1, 2) - se3.hat(shift) @ np.swapaxes(dp_v, 1, 2)),
                            rot_t @ np.swapaxes(dd, 1, 2), rot_t @ np.swapaxes(dp_v, 1, 2)], axis=1)   # [M, 9, 3]
        y = np.einsum("pij,pj->pi", k[j], differ)
        own = np.einsum("pij,pj->pi", rot_t[j], grad[role])                    # the slice's gradient, its frame
        lever = (rot_t @ (p - shift)[:, :, None])[:, :, 0][j] + tt[:, None] * (rot_t @ d[:, :, None])[:, :, 0][j]
        sign = -1.0 if role == 0 else 1.0
        values[:, role, :3] = y[:, :3] + tt[:, None] * y[:, 3:6] + sign * np.cross(lever, own)
        values[:, role, 3:] = y[:, 6:] + sign * own

    two_threads(derive)                                                    # the pairs' first and second slices
    values *= (term.sw / noise)[:, None, None]
    return PointJacobian(values, col[pairs], np.asarray(j), term.t_of, 6 * int((col >= 0).sum()))
