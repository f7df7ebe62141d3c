"""Draw ``docs/figures/pipeline.png``: the stages a request goes through (the home page's diagram, a
picture so that it shows without a network: the site's readers may be on a hospital network).

    .venv/bin/python tools/pipeline_figure.py
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "docs" / "figures" / "pipeline.png"
ROWS = (
    ("Each stack", ("Read: NIfTI, NRRD,\nMHA, DICOM", "Mask uploaded? If not:\nlocaliser network",
                    "N4 bias\ncorrection", "Per slice: mask,\nrescale, centre")),
    ("All slices at once", ("Pose network:\nMC dropout, 8 views", "Twin-aware SE(3)\nmean, variance")),
    ("Consistency", ("Per stack: branch,\nmotion model", "Stacks\npooled", "Image consistency\nwhere stacks cross")),
)
OUTPUTS = ("Response: pose, variance,\nexpected error per slice",
           "Reconstruction job: stack registration,\nSVR, atlas frame -> volume, preview, refined poses")
BOX_W, BOX_H, GAP = 2.3, 0.8, 0.45


def box(ax: plt.Axes, x: float, y: float, text: str, colour: str, width: float = BOX_W) -> None:
    ax.add_patch(FancyBboxPatch((x, y), width, BOX_H, boxstyle="round,pad=0.04", fc=colour, ec="#3f51b5", lw=1.2))
    ax.text(x + width / 2, y + BOX_H / 2, text, ha="center", va="center", fontsize=9)


def arrow(ax: plt.Axes, start: tuple[float, float], end: tuple[float, float]) -> None:
    ax.add_patch(FancyArrowPatch(start, end, arrowstyle="-|>", mutation_scale=12, lw=1.2, color="#333333"))


def main() -> None:
    left, step = 2.0, BOX_H + 0.6
    fig, ax = plt.subplots(figsize=(12, 6.4))
    ax.set_xlim(0, left + 4 * (BOX_W + GAP))
    ax.set_ylim(-(len(ROWS) + 1) * step - 0.1, BOX_H + 0.1)
    ax.axis("off")
    box(ax, left, 0.0, "Upload: stacks,\noptional masks", "#fff3e0")
    y = 0.0
    for title, stages in ROWS:
        y -= step
        ax.text(0.1, y + BOX_H / 2, title, fontsize=10, fontweight="bold", color="#3f51b5", va="center")
        arrow(ax, (left + BOX_W / 2, y + step), (left + BOX_W / 2, y + BOX_H))
        for i, text in enumerate(stages):
            x = left + i * (BOX_W + GAP)
            box(ax, x, y, text, "#e8eaf6")
            if i:
                arrow(ax, (x - GAP, y + BOX_H / 2), (x, y + BOX_H / 2))
    out_y, last = y - step, left + (len(ROWS[-1][1]) - 1) * (BOX_W + GAP) + BOX_W / 2
    ax.text(0.1, out_y + BOX_H / 2, "Answers", fontsize=10, fontweight="bold", color="#2e7d32", va="center")
    for i, text in enumerate(OUTPUTS):
        x, width = left + i * 4.0, 3.3 + 1.9 * i
        box(ax, x, out_y, text, "#e8f5e9", width)
        arrow(ax, (last, y), (x + width / 2, out_y + BOX_H))
    fig.savefig(OUT, dpi=110, bbox_inches="tight", facecolor="white")


if __name__ == "__main__":
    main()
