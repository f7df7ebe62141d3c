"""The training data: fetal atlas volumes in the one atlas space, and their split by whole volume.

``../shared/data/fetal_atlas`` holds two populations on the same 0.8 mm RAS grid (see its README):
the CRL spatio-temporal atlas (``crl_sta``, research use only) and the spina-bifida atlas
(``spina_bifida_cc0``, CC0). Neighbouring weeks look alike, so validation uses whole held-out
volumes of both populations (:data:`VALIDATION_VOLUMES`), never slices of a training volume. A run
may hold out others (``TrainConfig.val_volumes``): its checkpoint and the model exported from it
record them, and a model is evaluated and calibrated on its own (:func:`validation_volumes`).

A *packed* folder (:func:`pack`, ``svrnet-train pack``) holds the same volumes as one ``.npz`` each
(image and mask cropped to the image's non-zero box, exact float32, the affine moved with the crop)
and a ``packed.json`` index: it reads with numpy alone (no SimpleITK on a GPU host), and every
function here accepts it as ``root`` in place of the atlas folder.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

SHARED_DATA = Path(os.environ.get("SVRNET_SHARED_DATA")
                   or Path(__file__).resolve().parents[1].parent / "shared" / "data")
"""The project's data (the atlases, the real scans): ``../shared/data`` beside a checkout, or the folder
``SVRNET_SHARED_DATA`` names (an installed package has no checkout beside it)."""
DEFAULT_ATLAS_ROOT = SHARED_DATA / "fetal_atlas"
ATLAS_ID = "fetal-atlas-ras-0.8mm-135x189x155"
POPULATIONS = {
    "crl_sta": "CRL fetal brain atlas (Gholipour et al. 2017), non-commercial research use only",
    "spina_bifida_cc0": "Fetal spina bifida atlas (Fidon et al. 2021), CC0 1.0",
}
VALIDATION_VOLUMES = ("STA24", "STA31", "STA36", "SB_GA22_notoperated", "SB_GA29_operated")


def signed_distance(inside: NDArray, spacing: NDArray | None = None) -> NDArray[np.float32]:
    """Each voxel's Euclidean distance to the boundary of the boolean mask ``inside`` (in units of
    ``spacing``, default voxels), negative inside: how far outside (or how deep inside) the brain.

    Example:
        >>> m = np.zeros(7, bool); m[2:5] = True
        >>> signed_distance(m).tolist()
        [2.0, 1.0, -1.0, -2.0, -1.0, 1.0, 2.0]
    """
    inside = np.asarray(inside, bool)
    return (ndimage.distance_transform_edt(~inside, sampling=spacing)
            - ndimage.distance_transform_edt(inside, sampling=spacing)).astype(np.float32)


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

    def relative_depth(self, poses: NDArray) -> NDArray[np.float64]:
        """``|Tz - middle| / half-extent`` of planes ``poses [N, 4, 4]`` (plane frame -> atlas mm, the
        plane's normal its third column, its origin on the plane) in this brain: 0 at the middle
        along the normal, 1 at the brain's edge.

        Example (a brain filling x in 0..10 mm; planes normal to x at 5, 7.5 and 10 mm, each
        crossed at another in-plane point, which does not change its depth):
            >>> mask = np.ones((11, 3, 3), np.float32)
            >>> vol = AtlasVolume("toy", "toy", mask, mask, np.eye(4))
            >>> poses = np.stack([np.eye(4)] * 3)
            >>> poses[:, :3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]          # plane z -> atlas x
            >>> poses[:, :3, 3] = [[5, 1, 1], [7.5, 0, 2], [10, 2, 0]]
            >>> vol.relative_depth(poses).round(2).tolist()
            [0.0, 0.5, 1.0]
        """
        poses = np.asarray(poses, dtype=np.float64)
        normal = poses[:, :3, 2] / np.linalg.norm(poses[:, :3, 2], axis=1, keepdims=True)
        lo, hi = self.extent_along(normal)
        tz = np.einsum("ij,ij->i", poses[:, :3, 3] - self.centre, normal)
        return np.abs(tz - (lo + hi) / 2.0) / ((hi - lo) / 2.0)


def list_volumes(root: Path = DEFAULT_ATLAS_ROOT) -> list[tuple[str, str, Path, Path]]:
    """``(name, population, t2_path, mask_path)`` of every atlas volume under ``root``.

    For a packed folder both paths are the volume's ``.npz``.
    """
    index = Path(root) / PACKED_INDEX
    if index.exists():
        return [(n, pop, Path(root) / f"{n}.npz", Path(root) / f"{n}.npz")
                for n, pop in json.loads(index.read_text())["volumes"]]
    out = []
    for population in POPULATIONS:
        for t2 in sorted((root / population).glob("*_T2.nii.gz")):
            name = t2.name[: -len("_T2.nii.gz")]
            out.append((name, population, t2, t2.with_name(f"{name}_mask.nii.gz")))
    if not out:
        raise FileNotFoundError(f"no atlas volumes under {root}: it holds neither {' nor '.join(f'{p}/*_T2.nii.gz' for p in POPULATIONS)} "
                                f"(the atlases of ../shared/data/fetal_atlas) nor a {PACKED_INDEX} (svrnet-train pack): give --root, "
                                "or set SVRNET_SHARED_DATA to the folder that holds fetal_atlas/")
    return out


def load_volumes(names: list[str] | None = None, root: Path = DEFAULT_ATLAS_ROOT) -> list[AtlasVolume]:
    """Load the named volumes (default: all)."""
    vols = []
    for name, population, t2, mask in list_volumes(root):
        if names is not None and name not in names:
            continue
        if t2.suffix == ".npz":
            with np.load(t2) as z:
                vols.append(AtlasVolume(name, population, z["image"], z["mask"].astype(np.float32), z["affine"]))
            continue
        from service.io.volume import read_volume   # SimpleITK: only for the NIfTI atlas

        img = read_volume(t2)
        msk = read_volume(mask)
        vols.append(AtlasVolume(name, population, img.array.astype(np.float32),
                                (msk.array > 0.5).astype(np.float32), img.affine))
    return vols


PACKED_INDEX = "packed.json"


def pack(out: Path, root: Path = DEFAULT_ATLAS_ROOT, names: list[str] | None = None, compressed: bool = True) -> Path:
    """Write every atlas volume of ``root`` (or those of ``names``) as ``out/<name>.npz`` plus the
    ``packed.json`` index; ``compressed`` False stores them uncompressed, for an archiver that
    compresses better than zip's deflate (``tar -cJf``: about 17 against 30 MB for all 28 volumes,
    which then travel to a GPU host beside the repository).

    Voxels outside the image's non-zero box are zero, and slice sampling pads with zeros, so the
    crop changes nothing that the simulation sees; the affine's origin moves with it.

    Example:
        >>> import tempfile                                          # doctest: +SKIP
        >>> pack(Path(tempfile.mkdtemp()))                           # doctest: +SKIP
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    entries = []
    save = np.savez_compressed if compressed else np.savez
    for vol in load_volumes(names, root):
        nz = np.argwhere((vol.image != 0) | (vol.mask > 0))
        lo, hi = nz.min(0), nz.max(0) + 1
        box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))
        affine = vol.affine.copy()
        affine[:3, 3] = vol.affine[:3, :3] @ lo + vol.affine[:3, 3]
        save(out / f"{vol.name}.npz", image=np.ascontiguousarray(vol.image[box]),
             mask=np.ascontiguousarray(vol.mask[box] > 0.5), affine=affine)
        entries.append((vol.name, vol.population))
    (out / PACKED_INDEX).write_text(json.dumps({"volumes": entries}, indent=1))
    return out


def training_volumes(root: Path = DEFAULT_ATLAS_ROOT) -> list[str]:
    """Names of the volumes of ``root`` that are not :data:`VALIDATION_VOLUMES` (a folder packed
    with the training volumes alone holds no others; :func:`split` wants both)."""
    return [name for name, *_ in list_volumes(root) if name not in VALIDATION_VOLUMES]


def split(root: Path = DEFAULT_ATLAS_ROOT,
          validation: Sequence[str] = VALIDATION_VOLUMES) -> tuple[list[str], list[str]]:
    """Names of the training and validation volumes of ``root``, in its order (``validation``: the
    names held out, each of which ``root`` must hold)."""
    names = [n for n, *_ in list_volumes(root)]
    missing = set(validation) - set(names)
    if missing:
        raise ValueError(f"validation volumes not found: {sorted(missing)}")
    return [n for n in names if n not in validation], [n for n in names if n in validation]


HELD_OUT = "validation held out: "
"""What precedes the validation volumes in an exported model's ``training_data`` metadata."""


def validation_volumes(record: Mapping) -> list[str]:
    """The validation volumes of a trained model: those its checkpoint dict records
    (``config["val_volumes"]``), or, for an exported model's metadata, its ``validation_volumes``
    entry (comma-separated), else the names its ``training_data`` gives after :data:`HELD_OUT`;
    :data:`VALIDATION_VOLUMES` for a record that names none (a checkpoint of a run that recorded no split).

    Every evaluation and calibration of a model uses these: a run that held out its own volumes
    trained on the fixed ones, which must not judge it.

    Example:
        >>> validation_volumes({"config": {"val_volumes": ["STA30", "STA33"]}})
        ['STA30', 'STA33']
        >>> validation_volumes({"validation_volumes": "STA30,STA33"})
        ['STA30', 'STA33']
        >>> validation_volumes({"training_data": "2 atlas volumes (STA21, STA22); validation held out: STA30, STA33"})
        ['STA30', 'STA33']
        >>> validation_volumes({"config": {}}) == list(VALIDATION_VOLUMES)
        True
    """
    recorded = (record.get("config") or {}).get("val_volumes")
    if recorded:
        return list(recorded)
    if record.get("validation_volumes"):
        return [n.strip() for n in str(record["validation_volumes"]).split(",") if n.strip()]
    text = str(record.get("training_data", ""))
    if HELD_OUT in text:
        return [n.strip() for n in text.split(HELD_OUT, 1)[1].split(",") if n.strip()]
    return list(VALIDATION_VOLUMES)


def held_out_volumes(record: Mapping, root: Path = DEFAULT_ATLAS_ROOT) -> list[AtlasVolume]:
    """The loaded :func:`validation_volumes` of a model (its checkpoint dict or its file's metadata)
    that ``root`` holds, in ``root``'s order: what an evaluation or calibration of it runs on."""
    return load_volumes(split(root, validation_volumes(record))[1], root)
