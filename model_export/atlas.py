"""The training data: fetal atlas volumes in the one atlas space, and their split by whole volume.

``../shared/data/fetal_atlas`` holds two populations on the same 0.8 mm RAS grid (see its README):
the CRL spatio-temporal atlas (``crl_sta``, research use only) and the spina-bifida atlas
(``spina_bifida_cc0``, CC0). Neighbouring weeks look alike, so validation uses whole held-out
volumes of both populations (:data:`VALIDATION_VOLUMES`), never slices of a training volume.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from service.io.volume import read_volume

DEFAULT_ATLAS_ROOT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "fetal_atlas"
ATLAS_ID = "fetal-atlas-ras-0.8mm-135x189x155"
POPULATIONS = {
    "crl_sta": "CRL fetal brain atlas (Gholipour et al. 2017), non-commercial research use only",
    "spina_bifida_cc0": "Fetal spina bifida atlas (Fidon et al. 2021), CC0 1.0",
}
VALIDATION_VOLUMES = ("STA24", "STA31", "STA36", "SB_GA22_notoperated", "SB_GA29_operated")


@dataclass
class AtlasVolume:
    """One atlas volume with its brain mask, ready for slice simulation.

    Attributes:
        name: e.g. ``STA24`` or ``SB_GA22_notoperated``.
        population: folder name (``crl_sta`` or ``spina_bifida_cc0``).
        image: ``[I, J, K]`` float32 T2 intensities.
        mask: ``[I, J, K]`` float32 0/1 brain mask.
        affine: voxel -> atlas RAS mm.
        centre: brain (mask) centroid, atlas mm.
        surface: ``[M, 3]`` a subsample of mask points (atlas mm) to measure extents along normals.
    """

    name: str
    population: str
    image: NDArray[np.float32]
    mask: NDArray[np.float32]
    affine: NDArray[np.float64]
    centre: NDArray[np.float64] = field(init=False)
    surface: NDArray[np.float64] = field(init=False)

    def __post_init__(self) -> None:
        idx = np.argwhere(self.mask > 0.5)
        pts = idx @ self.affine[:3, :3].T + self.affine[:3, 3]
        self.centre = pts.mean(axis=0)
        self.surface = pts[:: max(1, len(pts) // 4000)]

    def extent_along(self, normals: NDArray) -> tuple[NDArray, NDArray]:
        """Lowest and highest offsets ``[N]`` of the brain along unit ``normals [N, 3]`` from the centre."""
        proj = (self.surface - self.centre) @ np.asarray(normals).T
        return proj.min(axis=0), proj.max(axis=0)


def list_volumes(root: Path = DEFAULT_ATLAS_ROOT) -> list[tuple[str, str, Path, Path]]:
    """``(name, population, t2_path, mask_path)`` of every atlas volume under ``root``."""
    out = []
    for population in POPULATIONS:
        for t2 in sorted((root / population).glob("*_T2.nii.gz")):
            name = t2.name[: -len("_T2.nii.gz")]
            out.append((name, population, t2, t2.with_name(f"{name}_mask.nii.gz")))
    if not out:
        raise FileNotFoundError(f"no atlas volumes under {root}")
    return out


def load_volumes(names: list[str] | None = None, root: Path = DEFAULT_ATLAS_ROOT) -> list[AtlasVolume]:
    """Load the named volumes (default: all)."""
    vols = []
    for name, population, t2, mask in list_volumes(root):
        if names is not None and name not in names:
            continue
        img = read_volume(t2)
        msk = read_volume(mask)
        vols.append(AtlasVolume(name, population, img.array.astype(np.float32),
                                (msk.array > 0.5).astype(np.float32), img.affine))
    return vols


def split(root: Path = DEFAULT_ATLAS_ROOT,
          validation: tuple[str, ...] = VALIDATION_VOLUMES) -> tuple[list[str], list[str]]:
    """Names of the training and validation volumes."""
    names = [n for n, *_ in list_volumes(root)]
    missing = set(validation) - set(names)
    if missing:
        raise ValueError(f"validation volumes not found: {sorted(missing)}")
    return [n for n in names if n not in validation], [n for n in names if n in validation]
