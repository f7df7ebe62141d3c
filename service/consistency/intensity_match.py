"""Slices' intensities matched where they cross: each stack's gain, odd-even step and in-plane shading.

The image term (:mod:`service.consistency.intersections`) compares two slices' intensities on the
line where they cross. Scanners do not keep every slice on one scale: an interleaved single-shot
acquisition's odd and even slices differ by their spin history, a receive coil's fall-off stays
in the scanner while the fetus moves, and N4 over a brain removes
only part of a field that changes across it. Each stack is scaled by its median brain intensity
(:class:`~service.consistency.slice_images.BlockedStack`); what is left makes crossing slices of
whole-uterus stacks disagree at their true poses by as much as they do at poses millimetres off,
and the refinement then trades one mismatch for another.

Before each pass of the refinement from the second on
(:data:`~service.consistency.image_refinement.MATCHED_FROM_PASS`), a log-linear model of those
differences is fitted to both slices' values on every line at the pass's starting poses, by
weighted, robust least squares:

::

    log I_a(x) - log I_b(x) = f_s(a, x) - f_t(b, x)
    f_s(k, x) = c_s + e_s p_k + g_s . u(x)

for slice ``a`` of stack ``s`` and ``b`` of stack ``t``: ``c_s`` the stack's gain, ``e_s`` its
even slices' step from its odd ones (``p_k = +-1``, :func:`slice_basis`), ``g_s`` its in-plane
slope (per :data:`SLOPE_SCALE_MM`) at the point's place ``u(x)`` from the stack's image centre. The
pass then samples each slice's image divided by ``exp f``. Lines see only differences between
stacks: Gaussian priors (:data:`GAIN_SD`, :data:`SLOPE_SD`) hold at no change what they do not
tell. Four numbers a stack cannot follow a slice's anatomy: a gain per slice would also take up the
mean mismatch of a slice seen at a wrong pose, which is what moves it back, and a drift over the
stack a run of slices whose brain darkened (docs/reports/consistency-experiments.md).

Example (two stacks crossing on a line of 40 points, the second 20 % brighter everywhere):
    >>> a = np.linspace(0.5, 1.5, 40)
    >>> lines = np.stack([np.zeros(40, int), np.ones(40, int)])                    # each point's stack, per role
    >>> basis = np.array([[1.0, 1.0], [1.0, 1.0]])                                  # one slice each
    >>> fields = fit_fields(np.stack([a, 1.2 * a]), np.ones(40), lines, lines, np.zeros((2, 40, 2)), basis, 2)
    >>> step = fields.log_field(1, basis[1], np.zeros(2)) - fields.log_field(0, basis[0], np.zeros(2))
    >>> round(float(np.exp(step)), 2)
    1.2
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.consistency.intersections import ImageTerm
from service.consistency.slice_images import SampledStack

GAIN_SD = (0.15, 0.15)
"""Prior sd of a stack's log gain and odd-even step (``c``, ``e``): spin history and signal changes
of 10-30 %."""
SLOPE_SD = 0.3
"""Prior sd of a stack's in-plane log-intensity slope per :data:`SLOPE_SCALE_MM` (a coil's fall-off
over a brain: up to a factor of about 1.5 across 100 mm)."""
SLOPE_SCALE_MM = 100.0
"""The in-plane distance the slope is measured over."""
HUBER = 0.1
"""Log-intensity difference taken as one sd of a point's noise; beyond it a point's weight falls as
``HUBER / |r|``: tissue seen at wrong poses, not a field."""
MIN_VALUE = 0.2
"""Points where either slice's value (in units of its stack's median brain intensity) lies under this
take no part: the log of a value near 0 is noise."""
ROUNDS = 4
"""Reweighted least-squares rounds."""
TERMS = len(GAIN_SD) + 2
"""Numbers per stack: gain, odd-even step, two in-plane slopes."""


@dataclass
class Fields:
    """A request's fitted intensity fields: ``coefficients [S, 4]`` per stack (``c, e`` of the slice
    basis, :func:`slice_basis`, then the in-plane slopes along its rows and columns) and how many
    points took part."""

    coefficients: NDArray[np.float64]
    points: int

    def log_field(self, stack: int, basis: NDArray, u: NDArray) -> NDArray[np.float64]:
        """``[...]`` the log field of stack ``stack`` at slices of ``basis [..., 2]`` and in-plane
        places ``u [..., 2]`` (per :data:`SLOPE_SCALE_MM`)."""
        return basis @ self.coefficients[stack, :2] + u @ self.coefficients[stack, 2:]

    def stack_field(self, stack: int, slices: int, shape: tuple[int, int], pixel_mm: tuple[float, float],
                    ) -> NDArray[np.float32]:
        """``[slices, H, W]`` the field of stack ``stack`` on its image grid of ``shape`` pixels of
        ``pixel_mm``.

        Example (the odd-even step alone: even slices 1.1 x, odd ones / 1.1):
            >>> f = Fields(np.array([[0.0, np.log(1.1), 0.0, 0.0]]), 3)
            >>> f.stack_field(0, 2, (1, 2), (1.0, 1.0)).astype(float).round(3).tolist()
            [[[1.1, 1.1]], [[0.909, 0.909]]]
        """
        rows, cols = ((np.arange(n) - (n - 1) / 2.0) * p / SLOPE_SCALE_MM for n, p in zip(shape, pixel_mm))
        plane = self.coefficients[stack, 2] * rows[:, None] + self.coefficients[stack, 3] * cols[None, :]
        gains = slice_basis(np.arange(slices)) @ self.coefficients[stack, :2]
        return np.exp(gains[:, None, None] + plane[None]).astype(np.float32)


def slice_basis(local: NDArray) -> NDArray[np.float64]:
    """``[N, 2]`` the gain basis of slices ``local`` (their places in their stacks): 1, and the
    parity (+1 even, -1 odd).

    Example:
        >>> slice_basis(np.arange(3)).tolist()
        [[1.0, 1.0], [1.0, -1.0], [1.0, 1.0]]
    """
    parity = 1.0 - 2.0 * (np.asarray(local) % 2)
    return np.stack([np.ones(len(parity)), parity], axis=1)


def fit_fields(values: NDArray, weights: NDArray, slice_of: NDArray, stack_of: NDArray, u: NDArray,
               basis: NDArray, stacks: int) -> Fields:
    """The request's :class:`Fields` from both slices' ``values [2, P]`` at each point (per role:
    the pair's first and second slice), the points' ``weights [P]`` (masks), each point's slice
    (request index, ``[2, P]``) and its stack (``[2, P]``), its in-plane place ``u [2, P, 2]`` (per
    :data:`SLOPE_SCALE_MM`, from its stack's image centre), every slice's :func:`slice_basis` row
    (``basis [N, 2]``) and the request's number of ``stacks``."""
    v = np.asarray(values, np.float64)
    ok = np.isfinite(v).all(axis=0) & (v[0] > MIN_VALUE) & (v[1] > MIN_VALUE) & (np.asarray(weights) > 0)
    if not ok.any():
        return Fields(np.zeros((stacks, TERMS)), 0)
    p = int(ok.sum())
    design = np.zeros((p, stacks, TERMS))                          # dense: a few numbers a stack
    for role, sign in ((0, 1.0), (1, -1.0)):
        terms = np.concatenate([basis[np.asarray(slice_of[role])[ok]], np.asarray(u[role])[ok]], axis=1)
        design[np.arange(p), np.asarray(stack_of[role])[ok]] += sign * terms
    design = design.reshape(p, stacks * TERMS)
    y = np.log(v[0, ok]) - np.log(v[1, ok])
    w0 = np.asarray(weights, np.float64)[ok] / HUBER ** 2
    prior = np.diag(np.tile(1.0 / np.array([*GAIN_SD, SLOPE_SD, SLOPE_SD]) ** 2, stacks))
    w = w0
    for _ in range(ROUNDS):
        weighted = design * w[:, None]
        z = np.linalg.solve(design.T @ weighted + prior, weighted.T @ y)
        r = np.abs(y - design @ z)
        w = w0 * np.where(r > HUBER, HUBER / np.maximum(r, 1e-12), 1.0)
    if not np.isfinite(z).all():                                   # nothing the lines can tell
        return Fields(np.zeros((stacks, TERMS)), 0)
    return Fields(z.reshape(stacks, TERMS), p)


def matched(sampled: list[SampledStack], term: ImageTerm, atlas_from_slice: NDArray,
            stack_of: NDArray) -> tuple[list[SampledStack], Fields]:
    """``sampled`` (a pass's stacks; ``stack_of [N]`` each of the request's slices' stack) with each
    slice's image divided by its stack's field, fitted (:func:`fit_fields`) to the values at
    ``term``'s points at the poses ``atlas_from_slice``; and the fields."""
    values = term.values(atlas_from_slice)
    slices = term.pairs[term.pair_of].T                                       # [2, P] request slice indices
    stacks = np.asarray(stack_of)[slices]
    shape = np.array([s.images.shape[1:] for s in sampled], np.float64)      # [S, 2] rows, columns
    pixel = np.array([[1.0 / s.pixel_from_slice[0, 1], 1.0 / s.pixel_from_slice[1, 0]] for s in sampled])
    u = (term.pixels(atlas_from_slice) - (shape[stacks] - 1.0) / 2.0) * pixel[stacks] / SLOPE_SCALE_MM
    sizes = np.array([len(s.images) for s in sampled])
    basis = slice_basis(np.concatenate([np.arange(n) for n in sizes]))
    fields = fit_fields(values, term.sw ** 2, slices, stacks, u, basis, len(sampled))
    out = []
    for i, s in enumerate(sampled):
        one = copy.copy(s)
        one.images = s.images / fields.stack_field(i, len(s.images), s.images.shape[1:], tuple(pixel[i]))
        out.append(one)
    return out, fields
