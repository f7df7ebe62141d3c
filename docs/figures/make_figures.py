"""Draw the documentation's pictures from a synthetic phantom brain (never from atlas data).

Two figures, written beside this script:

* ``slices_in_atlas.png``: three stacks (axial, coronal, sagittal) acquired from a moving phantom,
  every slice drawn where it really lies in atlas space, which is what ``/v1/predict`` returns
  (each slice's ``atlas_from_voxel``);
* ``reconstruction.png``: orthogonal planes of the phantom, and of the service's reconstruction
  (``service.reconstruction.reconstruct``: Gaussian average and super-resolution, no registration)
  of the same slices twice: where their stacks' files place them (the motion ignored), and at each
  slice's own pose (here the simulation's truth).

The phantom is an analytic, left-right symmetric head-sized shape (two hemispheres with a midline
fissure, a cortical ribbon, lateral ventricles, a cerebellum); its coordinates are atlas RAS mm.

Run from the repository root (a few seconds on two CPU cores)::

    .venv/bin/python docs/figures/make_figures.py

Figures of a real scan show a reconstruction job's volume (the job's own output file; the scan is not
in the repository)::

    .venv/bin/python docs/figures/make_figures.py --real recon.nii.gz [--name real_scan_reconstruction.png]

and each stack's largest brain slice beside the job's volume fetched in that stack's scanner
coordinates (``svrnet fetch JOB --stack-space N``), cut where the slice lies::

    .venv/bin/python docs/figures/make_figures.py --overlay axial.nii.gz recon_stack0.nii.gz \
        --overlay coronal.nii.gz recon_stack1.nii.gz [--name stack_space_overlay.png]
"""

from __future__ import annotations

import argparse
import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

os.environ.setdefault("MPLBACKEND", "Agg")
import matplotlib.pyplot as plt  # noqa: E402
from contourpy import contour_generator  # noqa: E402
from PIL import Image  # noqa: E402

from service.geometry import se3  # noqa: E402
from service.geometry.pose import apply  # noqa: E402
from service.geometry.sampling import sample_points  # noqa: E402
from service.io.volume import Volume  # noqa: E402
from service.reconstruction.config import ReconstructionConfig  # noqa: E402
from service.reconstruction.pipeline import reconstruct  # noqa: E402
from service.reconstruction.slices import SliceSet  # noqa: E402

HERE = Path(__file__).resolve().parent
STACK_COLOURS = ("#1f77b4", "#d62728", "#2ca02c")
STACK_NAMES = ("axial", "coronal", "sagittal")
RADII_MM = np.array([38.0, 46.0, 36.0])
"""Half-axes of the phantom's brain (x left-right, y posterior-anterior, z inferior-superior)."""


@dataclass
class Phantom:
    """A phantom volume in atlas space.

    Attributes:
        image: ``[I, J, K]`` T2-like intensities (CSF bright, tissue darker, 0 outside).
        mask: ``[I, J, K]`` brain mask.
        affine: voxel -> atlas RAS mm.
    """

    image: NDArray[np.float32]
    mask: NDArray[np.bool_]
    affine: NDArray[np.float64]


@dataclass
class Stack:
    """One simulated stack as a scanner writes it, and the truth the figures need.

    Attributes:
        name: ``axial``, ``coronal`` or ``sagittal``.
        image: ``[I, J, K]`` intensities; the slice axis is the one of largest spacing.
        mask: ``[I, J, K]`` brain mask on the stack's grid.
        affine: voxel -> scanner mm (the file's geometry; scanner and atlas frames coincide when
            the fetus does not move).
        slice_axis: the slice axis.
        atlas_from_voxel: ``[n, 4, 4]`` the true map of each slice's voxels into atlas mm.
    """

    name: str
    image: NDArray[np.float32]
    mask: NDArray[np.bool_]
    affine: NDArray[np.float64]
    slice_axis: int
    atlas_from_voxel: NDArray[np.float64]


def make_phantom(spacing_mm: float = 1.0) -> Phantom:
    """A symmetric brain-like phantom on a ``spacing_mm`` grid (see the module docstring).

    Args:
        spacing_mm: voxel size.

    Returns:
        The :class:`Phantom`.
    """
    half = RADII_MM + 8.0
    shape = tuple(int(v) for v in np.ceil(2 * half / spacing_mm) + 1)
    affine = np.diag([spacing_mm] * 3 + [1.0])
    affine[:3, 3] = -half
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1)
    xyz = ijk * spacing_mm + affine[:3, 3]
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    radius = np.sqrt((((xyz - [0.0, 0.0, 4.0]) / RADII_MM) ** 2).sum(-1))
    gyri = 0.035 * np.cos(0.32 * y + 0.2 * z) * np.cos(0.3 * z - 0.25 * np.abs(x)) + 0.02 * np.cos(0.5 * np.abs(x) + 0.4 * y)
    depth = radius + gyri                                           # folded depth below the surface
    cerebellum = np.sqrt(((xyz - [0.0, -30.0, -22.0]) ** 2 / np.array([22.0, 12.0, 10.0]) ** 2).sum(-1)) <= 1
    fissure = (np.abs(x) < 1.5) & (z > -6.0)
    mask = ((radius <= 1.0) & ~fissure) | cerebellum
    rng = np.random.default_rng(7)
    texture = ndimage.gaussian_filter(rng.normal(size=shape), 2.0)
    texture = 0.5 * (texture + texture[::-1])                   # keep the left-right symmetry
    image = 105.0 + 90.0 * texture                                  # white matter
    image[(depth > 0.84) & (radius <= 1.0)] = 60.0                  # cortical ribbon, dark on T2
    image[(depth > 0.93) & (radius <= 1.0)] = 225.0                 # sulci and extra-axial CSF, bright
    for side in (-1.0, 1.0):                                        # lateral ventricles
        c = np.array([side * 9.0, 2.0, 10.0])
        vent = (((xyz - c) / [5.0, 24.0, 7.0]) ** 2).sum(-1) <= 1.0
        image[vent] = 250.0
    image[(np.abs(x) < 3.0) & (np.abs(y + 2.0) < 14.0) & (np.abs(z + 8.0) < 8.0)] = 80.0   # deep grey matter
    folia = cerebellum & (radius > 0.9)
    image[folia] = np.where(np.cos(1.2 * z[folia]) > 0, 115.0, 75.0)                      # cerebellar folia
    image = ndimage.gaussian_filter(np.where(mask, image, 0.0), 0.7).astype(np.float32)
    return Phantom(image, mask, affine)


def smooth_motion(n: int, rng: np.random.Generator, degrees: float, mm: float) -> NDArray[np.float64]:
    """``[n, 4, 4]`` rigid motion over ``n`` acquisitions: a smooth random path of the given size.

    Args:
        n: acquisitions (slices, in acquisition order).
        rng: random generator.
        degrees: largest rotation about the brain's centre.
        mm: largest translation.

    Returns:
        One ``atlas_from_scanner`` per acquisition.
    """
    t = np.linspace(0.0, 1.0, n)
    coefficients = rng.normal(size=(3, 6))
    path = sum(np.sin((k + 1) * np.pi * t)[:, None] * coefficients[k] for k in range(3))
    path /= np.abs(path).max(0, keepdims=True)
    twist = path * np.r_[[np.radians(degrees)] * 3, [mm] * 3]
    return se3.exp(twist)


def acquire(phantom: Phantom, axis: int, rng: np.random.Generator, *, inplane_mm: float = 2.0,
            thickness_mm: float = 4.0, size: int = 56) -> Stack:
    """Acquire one interleaved stack of thick slices from the moving phantom.

    Args:
        phantom: the phantom.
        axis: the slice axis, which is also the atlas axis of the stack's normal
            (0 sagittal, 1 coronal, 2 axial).
        rng: random generator (the fetus's motion).
        inplane_mm: pixel size.
        thickness_mm: slice thickness and spacing.
        size: pixels per in-plane side.

    Returns:
        The :class:`Stack`.
    """
    n = int(np.ceil(2 * (RADII_MM[axis] + 6.0) / thickness_mm))
    shape = [size, size, size]
    shape[axis] = n
    spacing = np.full(3, inplane_mm)
    spacing[axis] = thickness_mm
    tilt = se3.so3_exp(rng.normal(0.0, np.radians(8.0), 3))
    affine = np.eye(4)
    affine[:3, :3] = tilt * spacing
    affine[:3, 3] = [0.0, 0.0, 4.0] - affine[:3, :3] @ ((np.array(shape) - 1) / 2.0)
    order = np.r_[np.arange(0, n, 2), np.arange(1, n, 2)]           # interleaved, even slices first
    motion = np.empty((n, 4, 4))
    motion[order] = smooth_motion(n, rng, degrees=6.0, mm=4.0)
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1).astype(np.float64)
    per_slice = np.moveaxis(ijk, axis, 0)                           # [n, a, b, 3]
    normal = tilt[:, axis]
    image = np.zeros(per_slice.shape[:-1], np.float64)
    mask = np.zeros(per_slice.shape[:-1], np.float64)
    offsets = np.linspace(-0.5, 0.5, 5) * thickness_mm              # thick-slice profile
    weights = np.exp(-0.5 * (offsets / (thickness_mm / 2.355)) ** 2)
    for offset, weight in zip(offsets, weights / weights.sum()):
        scanner = apply(affine, per_slice) + offset * normal
        atlas = apply(motion[:, None, None], scanner)
        image += weight * sample_points(phantom.image, phantom.affine, atlas)
        mask += weight * sample_points(phantom.mask.astype(np.float32), phantom.affine, atlas)
    image = image * rng.normal(1.0, 0.03, image.shape) + np.abs(rng.normal(0.0, 3.0, image.shape))
    return Stack(STACK_NAMES[2 - axis], np.moveaxis(image, 0, axis).astype(np.float32),
                 np.moveaxis(mask > 0.5, 0, axis), affine, axis, motion @ affine)


def save_png(figure: plt.Figure, path: Path, colours: int = 128) -> None:
    """Write ``figure`` as a palette PNG (small enough to keep in the repository).

    Args:
        figure: the matplotlib figure.
        path: output file.
        colours: palette size.
    """
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100, facecolor="white")
    plt.close(figure)
    image = Image.open(buffer).convert("RGB").quantize(colours, method=Image.Quantize.MEDIANCUT)
    image.save(path, optimize=True)
    print(f"{path.name}: {path.stat().st_size / 1024:.0f} KB")


def slice_grid(stack: Stack, index: int, step: int = 1) -> tuple[NDArray, NDArray, NDArray]:
    """Atlas mm ``[a, b, 3]``, grey values ``[a, b]`` and mask ``[a, b]`` of slice ``index``, every ``step`` pixels."""
    image = np.take(stack.image, index, axis=stack.slice_axis)[::step, ::step]
    mask = np.take(stack.mask, index, axis=stack.slice_axis)[::step, ::step]
    a, b = [d for d in range(3) if d != stack.slice_axis]
    ia, ib = np.meshgrid(np.arange(0, stack.image.shape[a], step), np.arange(0, stack.image.shape[b], step),
                         indexing="ij")
    voxel = np.zeros(ia.shape + (3,))
    voxel[..., a], voxel[..., b] = ia, ib
    return apply(stack.atlas_from_voxel[index], voxel), image, mask


def brain_outlines(stack: Stack, index: int) -> list[NDArray]:
    """Atlas mm ``[m, 3]`` polylines of the brain mask's outline in slice ``index`` of ``stack``."""
    mask = np.take(stack.mask, index, axis=stack.slice_axis).astype(np.float64)
    if not mask.any():
        return []
    a, b = [d for d in range(3) if d != stack.slice_axis]
    lines = contour_generator(z=np.pad(mask, 1)).lines(0.5)
    outlines = []
    for line in lines:
        voxel = np.zeros((len(line), 3))
        voxel[:, a], voxel[:, b] = line[:, 1] - 1.0, line[:, 0] - 1.0    # contourpy: x = column, y = row
        outlines.append(apply(stack.atlas_from_voxel[index], voxel))
    return outlines


def figure_slices_in_atlas(stacks: list[Stack], path: Path) -> None:
    """Every slice of every stack at its atlas pose: the brain's outline in each, and three slices' pixels.

    Args:
        stacks: the stacks, with their true ``atlas_from_voxel``.
        path: output PNG.
    """
    figure = plt.figure(figsize=(9.6, 4.8))
    for panel in range(2):
        ax = figure.add_subplot(1, 2, panel + 1, projection="3d", computed_zorder=False)
        for stack, colour in zip(stacks, STACK_COLOURS):
            n = stack.atlas_from_voxel.shape[0]
            if panel == 0:
                for k in range(n):
                    for line in brain_outlines(stack, k):
                        ax.plot(*line.T, color=colour, linewidth=0.7, alpha=0.8)
            else:
                k = n // 2
                xyz, grey, mask = slice_grid(stack, k)
                shade = plt.cm.gray(np.clip(grey / 255.0, 0.0, 1.0))
                shade[..., 3] = np.where(mask, 1.0, 0.0)
                ax.plot_surface(*np.moveaxis(xyz, -1, 0), facecolors=shade, rstride=1, cstride=1,
                                linewidth=0, antialiased=False, shade=False)
                for line in brain_outlines(stack, k):
                    ax.plot(*line.T, color=colour, linewidth=1.6)
        ax.set(xlim=(-50, 50), ylim=(-55, 55), zlim=(-45, 55))
        ax.set_xlabel("x: right (mm)", fontsize=8)
        ax.set_ylabel("y: anterior (mm)", fontsize=8)
        ax.set_zlabel("z: superior (mm)", fontsize=8)
        ax.set_box_aspect((100, 110, 100))
        ax.view_init(elev=20, azim=-60)
        ax.tick_params(labelsize=7)
        ax.set_title(("the brain's outline in every slice" if panel == 0 else "the middle slice of each stack"),
                     fontsize=10)
    handles = [plt.Line2D([], [], color=c, linewidth=3) for c in STACK_COLOURS]
    figure.legend(handles, [f"{s.name} stack" for s in stacks], loc="lower center", ncol=3, frameon=False)
    figure.suptitle("Slices of three stacks, acquired while the fetus moved, placed in atlas space (phantom)",
                    fontsize=11)
    figure.subplots_adjust(left=0.0, right=0.97, bottom=0.08, top=0.9, wspace=0.05)
    save_png(figure, path)


def planes_through(volume: NDArray, affine: NDArray, centre_mm: NDArray) -> list[NDArray]:
    """Sagittal, coronal and axial planes of ``volume`` through ``centre_mm``, displayed RAS-up.

    Args:
        volume: ``[I, J, K]`` on an axis-aligned RAS grid.
        affine: its voxel -> atlas affine.
        centre_mm: the atlas point the planes pass through.

    Returns:
        Three 2D arrays, superior (or anterior for the axial plane) up.
    """
    i, j, k = np.round(np.linalg.solve(affine, np.r_[centre_mm, 1.0])[:3]).astype(int)
    return [volume[i].T[::-1], volume[:, j].T[::-1], volume[:, :, k].T[::-1]]


def on_grid(volume: Volume, grid_affine: NDArray, shape: tuple[int, int, int]) -> NDArray:
    """``volume`` resampled (trilinear) onto the grid of ``grid_affine`` and ``shape``."""
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1).astype(np.float64)
    return sample_points(volume.array, volume.affine, apply(grid_affine, ijk))


def figure_reconstruction(phantom: Phantom, stacks: list[Stack], path: Path) -> None:
    """Planes of the phantom, of the stacks reconstructed with motion ignored, and at their own poses.

    Args:
        phantom: the phantom (the truth).
        stacks: the stacks with their true per-slice poses.
        path: output PNG.
    """
    def slice_set(poses: list[NDArray]) -> SliceSet:
        """The stacks' slices (brain pixels) at ``poses``, one ``[n, 4, 4]`` array per stack."""
        return SliceSet.from_stacks([(Volume(s.image, s.affine), s.mask.astype(np.float32), p,
                                      np.ones(len(p), bool)) for s, p in zip(stacks, poses)])

    bounds = np.array([-RADII_MM - 6, RADII_MM + 6]) + [0, 0, 4]
    config = ReconstructionConfig(register=False, coarse_to_fine=False)     # the poses as given, no registration
    file_grids = [np.repeat(s.affine[None], len(s.atlas_from_voxel), 0) for s in stacks]
    ignored = reconstruct(slice_set(file_grids), resolution_mm=1.0, svr_iterations=1, bounds_mm=bounds,
                          config=config)
    result = reconstruct(slice_set([s.atlas_from_voxel for s in stacks]), resolution_mm=1.0, svr_iterations=1,
                         bounds_mm=bounds, config=config)
    grid_affine, shape = result.volume.affine, result.volume.array.shape
    rows = [("phantom (truth)", on_grid(Volume(phantom.image, phantom.affine), grid_affine, shape)),
            ("stacks where their files put them\n(motion ignored)", on_grid(ignored.volume, grid_affine, shape)),
            ("reconstruction from each\nslice's own pose", result.volume.array)]
    centre = np.array([9.0, 0.0, 10.0])                # through a lateral ventricle
    figure, axes = plt.subplots(3, 3, figsize=(7.2, 7.6))
    for r, (label, volume) in enumerate(rows):
        planes = planes_through(volume, grid_affine, centre)
        top = np.percentile(volume[volume > 0], 99.5) if np.any(volume > 0) else 1.0
        for c, (plane, name) in enumerate(zip(planes, ("sagittal", "coronal", "axial"))):
            ax = axes[r, c]
            ax.imshow(plane, cmap="gray", vmin=0.0, vmax=top, aspect="equal", interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(name, fontsize=10)
            if c == 0:
                ax.set_ylabel(label, fontsize=9)
    figure.suptitle("Three stacks of 4 mm slices with motion, reconstructed at 1 mm (phantom)", fontsize=11)
    figure.tight_layout()
    save_png(figure, path)


def figure_real_scan(recon: Path, path: Path) -> None:
    """The three planes of atlas space through a reconstruction job's volume
    (:func:`service.reconstruction.preview.atlas_planes`, the job's preview's: neurological
    convention), larger than the job's own preview."""
    from service.io.volume import read_volume
    from service.reconstruction.preview import atlas_planes

    panels = atlas_planes(read_volume(recon))
    figure, axes = plt.subplots(1, 3, figsize=(10.5, 3.8), gridspec_kw={"width_ratios": [p.shape[1] for p in panels]})
    for ax, panel, name in zip(axes, panels, ("sagittal", "coronal", "axial")):
        ax.imshow(np.asarray(panel), cmap="gray", vmin=0, vmax=255, interpolation="bilinear")
        ax.set_title(name, fontsize=10)
        ax.axis("off")
    figure.tight_layout()
    save_png(figure, path)


def figure_stack_overlay(pairs: list[tuple[Path, Path]], path: Path) -> None:
    """Per pair (a stack, the job's volume in that stack's scanner coordinates): the stack's slice that
    cuts most of the volume, and the volume sampled at that slice's voxel centres (scanner mm
    from the stack's file), side by side: where the placement is right they show one cut."""
    from service.geometry import sampling
    from service.geometry.pose import apply
    from service.io.volume import read_volume

    figure, axes = plt.subplots(len(pairs), 2, figsize=(5.6, 2.8 * len(pairs)), squeeze=False)
    for row, (stack_path, volume_path) in zip(axes, pairs):
        stack, volume = read_volume(stack_path), read_volume(volume_path)
        ijk = np.stack(np.meshgrid(*[np.arange(n) for n in stack.array.shape], indexing="ij"), -1).astype(np.float64)
        cut = sampling.sample_points(volume.array, volume.affine, apply(stack.affine, ijk))
        k = int(np.argmax((cut > 0).sum(axis=(0, 1))))                  # the slice that cuts most of the volume
        seen = cut[..., k]
        inside = np.argwhere(seen > 0)
        lo, hi = inside.min(0), inside.max(0) + 1
        for ax, image, title in zip(row, (stack.array[..., k], seen), (f"{stack_path.name.split('.')[0]}, slice {k}",
                                                                        "the volume, placed by this stack")):
            crop = np.rot90(image[lo[0]:hi[0], lo[1]:hi[1]])
            ax.imshow(crop, cmap="gray", vmin=0, vmax=np.percentile(crop[crop > 0], 99), interpolation="bilinear")
            ax.set_title(title, fontsize=9)
            ax.axis("off")
    figure.tight_layout()
    save_png(figure, path)


def main() -> None:
    """Draw the phantom's figures into this script's folder; with ``--real RECON``, the real scan's;
    with ``--overlay STACK VOLUME`` (repeated), the stacks beside the volume placed by them."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--real", type=Path, help="a reconstruction job's volume (NIfTI): draw its figure only")
    parser.add_argument("--overlay", nargs=2, type=Path, action="append", metavar=("STACK", "VOLUME"),
                        help="a stack and the job's volume in its scanner coordinates: draw their figure only")
    parser.add_argument("--name", help="the real scan's figure's file name (default real_scan_reconstruction.png, "
                                       "stack_space_overlay.png)")
    args = parser.parse_args()
    if args.real is not None:
        figure_real_scan(args.real, HERE / (args.name or "real_scan_reconstruction.png"))
        return
    if args.overlay:
        figure_stack_overlay([tuple(pair) for pair in args.overlay], HERE / (args.name or "stack_space_overlay.png"))
        return
    rng = np.random.default_rng(2026)
    phantom = make_phantom()
    stacks = [acquire(phantom, axis, rng) for axis in (2, 1, 0)]
    figure_slices_in_atlas(stacks, HERE / "slices_in_atlas.png")
    figure_reconstruction(phantom, stacks, HERE / "reconstruction.png")


if __name__ == "__main__":
    main()
