"""The localiser in two stages: a coarse pass finds the head, the full passes run on a window.

The shipped localiser runs its two passes (plain and mirrored) over the whole canvas of every
slice; on a whole-uterus stack most of the canvas is not head. This script measures the other
way: one plain pass on a coarser grid (``--coarse-mm``), the stack's geometry settled on it
(:func:`~service.preprocess.brain_shape.brain_from_probabilities`), then the two passes on the
learnt grid over a window of the brain's box and ``--margin-mm`` around it (at least
:data:`~service.preprocess.localiser_inputs.MIN_GRID_PX` pixels a side, the brain's slices and two
more). Where the window's result reaches its inner edge, or the coarse pass finds no brain, the
stack is localised over the whole canvas as shipped. It prints, per real stack, the Dice of both
against the manual mask (or both volumes where there is none), their agreement, the window's share
of the canvas, and both times, measured one after the other in this process.

    .venv/bin/python model_export/experiments/localiser_window.py ../shared/data/real_scans/mial_lausanne_t30 \\
        [SCAN ...] [--coarse-mm 4.0] [--margin-mm 25]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.localiser.evaluate import dice, masked_files  # noqa: E402
from service.io.volume import Volume, read_volume  # noqa: E402
from service.preprocess.brain_shape import brain_from_probabilities  # noqa: E402
from service.geometry.pose import index_reversal  # noqa: E402
from service.preprocess.localise import Localiser, reversed_slices  # noqa: E402
from service.preprocess.stack import stack_axis  # noqa: E402
from service.preprocess.localiser_inputs import MIN_GRID_PX, PAD_MULTIPLE, LocaliserGrid, localiser_inputs  # noqa: E402
from service.core.settings import DEFAULT_LOCALISERS_DIR  # noqa: E402


def _window(lo: float, hi: float, n: int) -> tuple[int, int]:
    """A window of whole :data:`PAD_MULTIPLE` pixels, at least :data:`MIN_GRID_PX`, centred on
    ``[lo, hi)`` and inside ``[0, n)``."""
    size = max(int(np.ceil((hi - lo) / PAD_MULTIPLE)) * PAD_MULTIPLE, MIN_GRID_PX)
    if size >= n:
        return 0, n
    start = min(max(int(round((lo + hi - size) / 2)), 0), n - size)
    return start, start + size


def coarse_to_fine(index: float, coarse: LocaliserGrid, fine: LocaliserGrid, axis: int, coarse_mm: float,
                   fine_mm: float) -> float:
    """Where pixel edge ``index`` of the padded coarse grid lies on the padded fine grid (both grids
    cover the slice's field of view from its corner, each padded by its own offset)."""
    return (index - coarse.offset[axis]) * coarse_mm / fine_mm + fine.offset[axis]


class WindowedLocaliser(Localiser):
    """:class:`Localiser` whose full passes run on the window a coarse pass finds (set
    ``coarse_mm``, ``margin_mm`` and ``share`` after :meth:`load`); ``share`` collects each stack's
    window share of the canvas (1.0 where it fell back to the whole canvas)."""

    def probabilities_of(self, volumes: list[Volume], grids_mm: list[float] | None = None,
                         ) -> list[tuple[NDArray[np.float32], LocaliserGrid]]:
        if grids_mm is not None:                        # a small brain's second look: the whole canvas
            return super().probabilities_of(volumes, grids_mm)
        return [self._in_order(v) for v in volumes]

    def _in_order(self, volume: Volume) -> tuple[NDArray[np.float32], LocaliserGrid]:
        """:meth:`_windowed` on the stack's slices in the order the service's localiser sees them
        (:func:`~service.preprocess.localise.reversed_slices`), the maps in the file's order."""
        if not reversed_slices(volume):
            return self._windowed(volume)
        axis = stack_axis(volume)
        turned = Volume(np.ascontiguousarray(np.flip(volume.array, axis)),
                        volume.affine @ index_reversal(axis, volume.array.shape[axis]))
        prob, grid = self._windowed(turned)
        return np.ascontiguousarray(prob[::-1]), grid

    def _windowed(self, volume: Volume) -> tuple[NDArray[np.float32], LocaliserGrid]:
        name = self.session.get_inputs()[0].name
        coarse, cgrid = localiser_inputs(volume, self.coarse_mm)
        plain = replace(self, mirrored=False)._logits(name, coarse)
        voxel_ml = self.coarse_mm ** 2 * float(volume.spacing[cgrid.slice_axis]) / 1000.0
        brain, _ = brain_from_probabilities(1.0 / (1.0 + np.exp(-plain)), voxel_ml, self.coarse_mm)
        if not brain.any():
            return self._whole(volume)
        x, grid = localiser_inputs(volume, self.grid_mm)
        n, h, w = len(x), *x.shape[2:]
        spans = [np.flatnonzero(brain.any(axis=a)) for a in ((1, 2), (0, 2), (0, 1))]
        def fine(i: float, a: int) -> float:
            return coarse_to_fine(i, cgrid, grid, a, self.coarse_mm, self.grid_mm)

        m = self.margin_mm / self.grid_mm
        r0, r1 = _window(fine(spans[1][0], 0) - m, fine(spans[1][-1] + 1, 0) + m, h)
        c0, c1 = _window(fine(spans[2][0], 1) - m, fine(spans[2][-1] + 1, 1) + m, w)
        s0, s1 = max(spans[0][0] - 2, 0), min(spans[0][-1] + 3, n)
        logits = np.full((n, h, w), -20.0, np.float32)
        logits[s0:s1, r0:r1, c0:c1] = self._logits(name, np.ascontiguousarray(x[s0:s1, :, r0:r1, c0:c1]))
        inner = np.zeros((h, w), bool)
        inner[r0:r1, c0:c1] = True
        core = np.zeros((h, w), bool)
        core[r0 + 2 * (r0 > 0):r1 - 2 * (r1 < h), c0 + 2 * (c0 > 0):c1 - 2 * (c1 < w)] = True
        if (logits[:, inner & ~core] > 0).any() or (s0 > 0 and (logits[s0] > 0).any()) or \
                (s1 < n and (logits[s1 - 1] > 0).any()):
            return self._whole(volume)
        self.share.append((s1 - s0) * (r1 - r0) * (c1 - c0) / (n * h * w))
        return 1.0 / (1.0 + np.exp(-logits)), grid

    def _whole(self, volume: Volume) -> tuple[NDArray[np.float32], LocaliserGrid]:
        self.share.append(1.0)
        return super().probabilities_of([volume])[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scans", nargs="+", type=Path, help="real scan folders (masks as NAME_brain_mask.nii.gz)")
    ap.add_argument("--model", type=Path, default=DEFAULT_LOCALISERS_DIR / "default" / "model.onnx")
    ap.add_argument("--coarse-mm", type=float, default=4.0)
    ap.add_argument("--margin-mm", type=float, default=25.0)
    args = ap.parse_args()
    whole, windowed = Localiser.load(args.model), WindowedLocaliser.load(args.model)
    windowed.coarse_mm, windowed.margin_mm, windowed.share = args.coarse_mm, args.margin_mm, []
    stacks = []
    for scan in args.scans:
        masked = {s.resolve() for _, s, _ in masked_files(scan)}
        stacks += [(name, read_volume(s), read_volume(m).array > 0) for name, s, m in masked_files(scan)]
        stacks += [(p.name, read_volume(p), None) for p in sorted(scan.glob("*.nii*"))
                   if "mask" not in p.name and p.resolve() not in masked]
    times = np.zeros(2)
    scores = []
    for name, volume, manual in stacks:
        whole.localise(volume)                                            # warm both
        windowed.localise(volume)
        t0 = time.perf_counter()
        a = whole.localise(volume)
        t1 = time.perf_counter()
        b = windowed.localise(volume)
        t2 = time.perf_counter()
        times += (t1 - t0, t2 - t1)
        found = (f"Dice {dice(a.mask, manual):.3f} / {dice(b.mask, manual):.3f}" if manual is not None
                 else f"{a.brain_volume_ml:.0f} / {b.brain_volume_ml:.0f} ml")
        if manual is not None:
            scores.append((dice(a.mask, manual), dice(b.mask, manual)))
        print(f"{name:28s} {found}  agree {dice(a.mask, b.mask):.3f}  window {windowed.share[-1]:.2f}  "
              f"{(t1 - t0) * 1e3:.0f} / {(t2 - t1) * 1e3:.0f} ms", flush=True)
    if scores:
        s = np.array(scores)
        print(f"median Dice {np.median(s[:, 0]):.3f} / {np.median(s[:, 1]):.3f}, minimum {s[:, 0].min():.3f} / "
              f"{s[:, 1].min():.3f}; ms a stack {times[0] / len(stacks) * 1e3:.0f} / {times[1] / len(stacks) * 1e3:.0f} "
              "(whole canvas / window)")


if __name__ == "__main__":
    main()
