"""Whether `/v1/predict`'s poses depend on where a scan's files place it in the scanner.

A file's world origin is the scanner's choice (its isocentre, the table position), not the fetus's:
moving every stack of a request by one shift in scanner mm changes nothing the network sees, so
``atlas_from_voxel`` should not change either. This script sends a real scan's stacks (with their
manual masks) to the app as they are and with their affines shifted, and prints, per shift and per
stack, the largest difference of the slices' atlas translations from the unshifted answer. Form
fields after the stack names (``image_consistency=false stack_consistency=false``) switch stages
off, to find the stage that depends on the origin.

    .venv/bin/python model_export/experiments/origin_shift.py ../shared/data/real_scans/mial_lausanne_t30 \\
        axial1_lr[,coronal1_lr,...] [FIELD=VALUE ...]
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from fastapi.testclient import TestClient  # noqa: E402

from service.core.settings import Settings  # noqa: E402
from service.inference.registry import ModelRegistry  # noqa: E402
from service.io.volume import Volume, read_volume, write_volume  # noqa: E402
from service.main import create_app  # noqa: E402

SHIFTS_MM = ([0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [0.0, -120.0, 80.0], [200.0, 150.0, -100.0])
MASK_SUFFIX = "_brain_mask.nii.gz"


def shifted_files(volumes: list[tuple[str, str, Volume]], shift: np.ndarray, folder: Path) -> list[tuple]:
    """The multipart files of ``(field, file name, volume)`` with every affine moved by ``shift``."""
    files = []
    for field, name, volume in volumes:
        affine = volume.affine.copy()
        affine[:3, 3] += shift
        path = folder / name
        write_volume(Volume(volume.array, affine), path)
        files.append((field, (path.name, path.read_bytes(), "application/gzip")))
    return files


def main() -> None:
    scan, names = Path(sys.argv[1]), sys.argv[2].split(",")
    fields = {"mc_samples": "30", **dict(arg.split("=", 1) for arg in sys.argv[3:])}
    volumes = [(field, f"{name}{suffix}", read_volume(scan / f"{name}{suffix}"))
               for field, suffix in (("stacks", ".nii.gz"), ("masks", MASK_SUFFIX)) for name in names]
    registry = ModelRegistry.from_directory(Path(__file__).resolve().parents[2] / "service" / "models")
    answers = {}
    with tempfile.TemporaryDirectory() as tmp, \
            TestClient(create_app(Settings(data_dir=Path(tmp) / "jobs"), registry=registry)) as client:
        for shift in SHIFTS_MM:
            r = client.post("/v1/predict", files=shifted_files(volumes, np.array(shift), Path(tmp)), data=fields)
            r.raise_for_status()
            answers[tuple(shift)] = [np.array([s["atlas_from_voxel"] for s in stack["slices"]])
                                     for stack in r.json()["stacks"]]
    base = answers[tuple(SHIFTS_MM[0])]
    for shift, stacks in answers.items():
        worst = [float(np.abs(a[:, :3, 3] - b[:, :3, 3]).max()) for a, b in zip(stacks, base)]
        print(f"shift {shift} mm: largest change of a slice's atlas translation per stack "
              f"{', '.join(f'{w:.3f}' for w in worst)} mm")


if __name__ == "__main__":
    main()
