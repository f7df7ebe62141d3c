"""The derivatives of the image term by each slice's pose, and the normal equations they give.

:func:`image_jacobian` differentiates the residuals of :class:`~service.consistency.intersections.ImageTerm`
(two slices' intensities at points of their intersection line) by a right perturbation of each
slice's pose in its network frame; :class:`PointJacobian` holds them as two 6-vectors per point,
laid out along each pair's line, and assembles ``J^T W J`` and ``J^T W r`` pair by pair for the
Levenberg-Marquardt steps of :func:`~service.consistency.image_refinement.refine`.

Example (one point of one pair, slices 1 and 0 of two free slices):
    >>> import numpy as np
    >>> jac = PointJacobian.of_points(np.ones((1, 2, 6)), np.array([[1, 0]]), np.array([0]), np.array([0]), 12)
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
from service.geometry import se3


@dataclass
class PointJacobian:
    """The image residuals' derivatives, laid out along each pair's line: ``lined [M, 12, L]`` holds
    the derivatives of the residual at place ``l`` of pair ``m``'s line by the twists of the pair's
    two slices (rows ``0..5`` the first's, ``6..11`` the second's), in the columns ``6 c + (0..5)`` of
    their free columns ``c = pair_cols[m]`` (``-1``: a slice that keeps its pose; its derivatives are
    0, as are those of places without a point). Point ``p`` lies at ``(pair_of[p], place[p])``. Every
    residual depends on two slices only, so the normal equations are assembled pair by pair
    (:meth:`normal`), with no sparse matrix, each pair's points in one small matrix product."""

    lined: NDArray[np.float64]
    pair_cols: NDArray[np.int64]          # [M, 2] each pair's slices' free columns
    pair_of: NDArray[np.int64]            # [P] each point's pair
    place: NDArray[np.int64]              # [P] its place along the pair's line (unique within a pair)
    n_params: int

    @classmethod
    def of_points(cls, values: NDArray, pair_cols: NDArray, pair_of: NDArray, place: NDArray,
                  n_params: int) -> "PointJacobian":
        """From two 6-vectors per point (``values [P, 2, 6]``: by the twist of its pair's first and
        second slice)."""
        lined = along_lines(np.asarray(values, np.float64).reshape(len(values), 12), pair_of, place, len(pair_cols))
        return cls(_without_fixed(lined, pair_cols), pair_cols, pair_of, place, n_params)

    @property
    def values(self) -> NDArray[np.float64]:
        """``[P, 2, 6]`` each point's derivatives by its pair's two slices' twists."""
        return self.lined[self.pair_of, :, self.place].reshape(len(self.pair_of), 2, 6)

    def sparse(self) -> sparse.csr_matrix:
        """``[P, n_params]`` the same derivatives as a sparse matrix."""
        cols = self.pair_cols[self.pair_of]                                   # [P, 2]
        ok = cols >= 0
        rows = np.repeat(np.nonzero(ok)[0], 6)
        return sparse.csr_matrix((self.values[ok].ravel(), (rows, (6 * cols[ok][:, None] + np.arange(6)).ravel())),
                                 shape=(len(self.pair_of), self.n_params))

    def normal(self, weights: NDArray, r: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``J^T W J`` (dense, ``[n_params, n_params]``) and ``J^T W r`` for point weights ``weights [P]``.

        Each pair's ``12 x 12`` block is one small matrix product over its line's places (all pairs
        in one batched product), then added into the four ``6 x 6`` blocks of its two slices.

        Example:
            >>> v = np.arange(12.0).reshape(1, 2, 6) / 10
            >>> jac = PointJacobian.of_points(v, np.array([[1, 0]]), np.array([0]), np.array([0]), 12)
            >>> h, g = jac.normal(np.array([2.0]), np.array([0.5]))
            >>> dense = jac.sparse().toarray()
            >>> bool(np.allclose(h, 2.0 * dense.T @ dense)), bool(np.allclose(g, dense[0]))
            (True, True)
        """
        n, pairs = self.n_params, len(self.pair_cols)
        if not len(self.pair_of):
            return np.zeros((n, n)), np.zeros(n)
        w = along_lines(np.stack([weights, weights * r], axis=1), self.pair_of, self.place, pairs,
                        self.lined.shape[2])                                      # [M, 2, L]
        blocks = (self.lined * w[:, :1]) @ np.swapaxes(self.lined, 1, 2)          # [M, 12, 12]
        per_pair = (self.lined @ w[:, 1, :, None])[:, :, 0]                       # [M, 12]
        index = (6 * np.maximum(self.pair_cols, 0)[:, :, None] + np.arange(6)).reshape(pairs, 12)
        hess = np.bincount((index[:, :, None] * n + index[:, None, :]).ravel(), blocks.ravel(), n * n).reshape(n, n)
        grad = np.bincount(index.ravel(), per_pair.ravel(), n)
        return hess, grad


def along_lines(per_point: NDArray, pair_of: NDArray, place: NDArray, pairs: int,
                places: int | None = None) -> NDArray[np.float64]:
    """``[P, C]`` per-point values laid out along the pairs' lines, ``[pairs, C, places]`` (default
    places: up to the last one used; 0 where no point lies).

    Example:
        >>> along_lines(np.array([[1.0], [2.0]]), np.array([0, 0]), np.array([0, 2]), 1).tolist()
        [[[1.0, 0.0, 2.0]]]
    """
    places = int(np.max(place, initial=-1)) + 1 if places is None else places
    out = np.zeros((pairs, places, per_point.shape[1]))
    out[pair_of, place] = per_point
    return np.ascontiguousarray(np.swapaxes(out, 1, 2))


def _without_fixed(lined: NDArray, pair_cols: NDArray) -> NDArray:
    """``lined`` with the derivatives by slices that keep their poses (column ``-1``) set to 0, in place."""
    for role in (0, 1):
        lined[pair_cols[:, role] < 0, 6 * role:6 * role + 6] = 0.0
    return lined


def image_jacobian(term: ImageTerm, atlas_from_slice: NDArray, poses: NDArray, col: NDArray,
                   noise: float) -> PointJacobian:
    """The image residuals' derivatives by each free slice's twist (its network frame), laid out
    along the pairs' lines (:class:`PointJacobian`).

    A slice moved by a small rigid motion ``(w, v)`` of the atlas moves the pair's line with it: its
    plane ``n . x = c`` turns (``dn = w x n``, ``dc = n . v``), the line's direction
    ``d = n_a x n_b / |n_a x n_b|`` turns, and the point of the line nearest the two slices' mean
    origin moves (``L dp = rhs``, ``L`` the rows ``n_a, n_b, d``). A point ``x = p + t d`` moves by
    ``dx``; the moved slice sees it at ``dx - (w x x + v)`` in its own frame, the other at ``dx``.
    So for ``r = I_a - I_b`` with gradients ``G_a``, ``G_b`` (atlas mm):
    ``dr = (G_a - G_b) . dx - G_a . (w x x + v)`` when ``a`` moves, ``... + G_b . (w x x + v)`` when
    ``b`` does; ``(w, v)`` is ``Ad(P) d`` of the twist ``d`` in the network frame of the slice's
    current pose ``P`` (``w = R d_w``, ``v = R d_v + t x w``). Along a pair's line all of this is
    linear in ``t`` and in the point's derivatives along both slices' pixel rows and columns: per
    pair and moving slice one ``9 x 4`` matrix, applied to every point of every line in one batched
    product. Checked
    against finite differences in the tests."""
    pixel, along = term.gradients(atlas_from_slice)
    pairs, j, place = term.pairs, term.pair_of, term.t_of
    # each point's pixel derivatives in both slices, along the lines, weighed as its residual is
    seen = along_lines(np.concatenate([pixel[0], pixel[1]], axis=1) * (term.sw / noise)[:, None],
                       j, place, len(pairs))                                # [M, 4, L]
    tt = term.t[:seen.shape[2]]                                            # each place's t
    ln = lines(atlas_from_slice, atlas_from_slice, pairs)
    na, nb, oa, ob, d, m, p = ln.na, ln.nb, ln.oa, ln.ob, ln.d, ln.m, ln.p
    inv = ln.inv                                                           # columns: dp per unit of each rhs
    perp = (np.eye(3) - d[:, :, None] * d[:, None, :]) / ln.size[:, None, None]
    lined = np.empty((len(pairs), 12, seen.shape[2]))

    def derive(role: int) -> None:
        n, o = (na, oa) if role == 0 else (nb, ob)
        dd = perp @ se3.hat(nb) @ se3.hat(na) if role == 0 else -perp @ se3.hat(na) @ se3.hat(nb)        # d(d)/dw
        q = np.einsum("mji,mj->mi", dd, m - p)
        c_own, c_line = inv[:, :, role], inv[:, :, 2]
        dp_w = -c_own[:, :, None] * np.cross(n, p)[:, None, :] + c_line[:, :, None] * (q + 0.5 * np.cross(o, d))[:, None, :]
        dp_v = c_own[:, :, None] * n[:, None, :] + 0.5 * c_line[:, :, None] * d[:, None, :]
        g = pairs[:, role]
        rot_t, shift = np.swapaxes(poses[g, :3, :3], 1, 2), poses[g, :3, 3]
        sign = -1.0 if role == 0 else 1.0
        # per pair, in the slice's network frame, with G = G_a - G_b and G_own the slice's gradient:
        # rotation: K1 G + t K2 G -+ (x - shift) x G_own, x - shift = (p - shift) + t d;
        # shift: K3 G -+ G_own
        k = np.concatenate([rot_t @ (np.swapaxes(dp_w, 1, 2) - se3.hat(shift) @ np.swapaxes(dp_v, 1, 2)),
                            rot_t @ np.swapaxes(dd, 1, 2), rot_t @ np.swapaxes(dp_v, 1, 2)], axis=1)   # [M, 9, 3]
        seen_own = sign * rot_t                                             # G_own in the slice's frame, signed
        own = np.concatenate([se3.hat((rot_t @ (p - shift)[:, :, None])[:, :, 0]) @ seen_own,
                              se3.hat((rot_t @ d[:, :, None])[:, :, 0]) @ seen_own, seen_own], axis=1)   # [M, 9, 3]
        # G_a = A_a P_a, G_b = A_b P_b (P a point's pixel derivatives, A its slice's ``along``)
        mine, other = (own + k, -k) if role == 0 else (own - k, k)
        by_pixel = np.concatenate([(mine if role == 0 else other) @ along[0],
                                   (other if role == 0 else mine) @ along[1]], axis=2)                   # [M, 9, 4]
        y = by_pixel @ seen                                                # [M, 9, L]
        at = 6 * role
        lined[:, at:at + 3] = y[:, 0:3] + tt * y[:, 3:6]
        lined[:, at + 3:at + 6] = y[:, 6:9]

    derive(0)                                                              # the pairs' first slices
    derive(1)                                                              # and their second
    return PointJacobian(_without_fixed(lined, col[pairs]), col[pairs], np.asarray(j), place, 6 * int((col >= 0).sum()))
