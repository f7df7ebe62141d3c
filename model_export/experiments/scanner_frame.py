"""Whether `/v1/predict`'s poses depend on how a scan's files place it in the scanner, or on the order of its stacks.

A file's scanner frame is the scanner's choice (its isocentre, the table position, the patient's
position on the table), not the fetus's: moving or turning every stack of a request by one rigid
map of scanner mm changes nothing the network sees, so ``atlas_from_voxel`` should not change;
nor should sending the same stacks in another order. This script sends a real scan's stacks (with
their manual masks) to the app as they are, with their affines moved (:data:`FRAMES`), and in
reverse order, and prints per variant and per stack how the slices both answers accept moved from
the answer to the files as they are: the median and largest move of a slice's centre (mm), the
largest turn (degrees). Form fields
after the stack names (``image_consistency=false stack_consistency=false``) switch stages off, to
find the stage that depends on the frame.

    .venv/bin/python model_export/experiments/scanner_frame.py ../shared/data/real_scans/mial_lausanne_t30 \\
        axial1_lr[,coronal1_lr,...] [FIELD=VALUE ...]
"""

from __future__ import annotations

import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from fastapi.testclient import TestClient  # noqa: E402

from service.core.settings import Settings  # noqa: E402
from service.geometry import se3  # noqa: E402
from service.geometry.pose import make_pose, translate  # noqa: E402
from service.inference.registry import ModelRegistry  # noqa: E402
from service.io.volume import Volume, read_volume, write_volume  # noqa: E402
from service.main import create_app  # noqa: E402

FRAMES = {
    "shift (50, 0, 0) mm": translate([50.0, 0.0, 0.0]),
    "shift (0, -120, 80) mm": translate([0.0, -120.0, 80.0]),
    "shift (200, 150, -100) mm": translate([200.0, 150.0, -100.0]),
    "turned 30 deg about (1, 1, 0), shifted (60, -40, 90) mm":
        make_pose(se3.so3_exp(np.radians(30.0) * np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)), [60.0, -40.0, 90.0]),
}
"""``moved_scanner_from_scanner`` of each variant: every file's affine becomes ``M @ affine``."""
MASK_SUFFIX = "_brain_mask.nii.gz"


def moved(volume: Volume, moved_from_scanner: np.ndarray) -> Volume:
    """``volume`` with its scanner frame moved: each voxel lands at ``moved_from_scanner`` of where it was.

    Example:
        >>> v = moved(Volume(np.zeros((2, 2, 2), np.float32), np.diag([2.0, 2.0, 3.0, 1.0])), translate([5.0, 0.0, 0.0]))
        >>> (v.affine @ [1.0, 1.0, 1.0, 1.0]).tolist()
        [7.0, 2.0, 3.0, 1.0]
    """
    return Volume(volume.array, np.asarray(moved_from_scanner, np.float64) @ volume.affine)


@dataclass
class StackAnswer:
    """What an answer says of one stack's slices: their centres in atlas mm, their rotations, accepted."""

    centres: np.ndarray          # [n, 3] the atlas position of each slice's centre voxel
    rotations: np.ndarray        # [n, 3, 3]
    accepted: np.ndarray         # [n] bool

    @classmethod
    def of(cls, stack: dict) -> "StackAnswer":
        """From one stack of a ``/v1/predict`` answer (its voxel grid's centre in each slice's plane)."""
        poses = np.array([s["atlas_from_voxel"] for s in stack["slices"]])
        voxels = np.tile(np.append((np.array(stack["shape"]) - 1) / 2.0, 1.0), (len(poses), 1))
        voxels[:, stack["slice_axis"]] = [s["index"] for s in stack["slices"]]
        return cls(np.einsum("nij,nj->ni", poses, voxels)[:, :3], poses[:, :3, :3],
                   np.array([s["accepted"] for s in stack["slices"]], bool))


def changes(answer: StackAnswer, base: StackAnswer) -> tuple[float, float, float, int]:
    """How one stack's slices moved between two answers, over the slices both accept: the median and
    largest move of a slice's centre (mm), the largest change of its rotation (degrees), and how
    many slices that is (NaN moves where there are none).

    Example:
        >>> still = StackAnswer(np.zeros((2, 3)), np.stack([np.eye(3)] * 2), np.array([True, True]))
        >>> turned = StackAnswer(np.array([[0.0, 0.5, 0.0], [0.0, 0.0, 0.0]]),
        ...                      np.stack([se3.so3_exp(np.radians([0.0, 0.0, 2.0])), np.eye(3)]), np.array([True, True]))
        >>> median, largest, turn, slices = changes(turned, still)
        >>> round(median, 3), round(largest, 3), round(turn, 3), slices
        (0.25, 0.5, 2.0, 2)
    """
    both = answer.accepted & base.accepted
    if not both.any():
        return float("nan"), float("nan"), float("nan"), 0
    moved = np.linalg.norm(answer.centres[both] - base.centres[both], axis=1)
    turned = np.degrees(np.linalg.norm(se3.so3_log(np.swapaxes(base.rotations[both], 1, 2) @ answer.rotations[both]), axis=-1))
    return float(np.median(moved)), float(moved.max()), float(turned.max()), int(both.sum())


def main() -> None:
    scan, names = Path(sys.argv[1]), sys.argv[2].split(",")
    fields = {"mc_samples": "30", **dict(arg.split("=", 1) for arg in sys.argv[3:])}
    volumes = {(field, name): read_volume(scan / f"{name}{suffix}")
               for field, suffix in (("stacks", ".nii.gz"), ("masks", MASK_SUFFIX)) for name in names}
    registry = ModelRegistry.from_directory(Path(__file__).resolve().parents[2] / "service" / "models")

    def ask(client: TestClient, folder: Path, frame: np.ndarray, order: list[str]) -> dict[str, StackAnswer]:
        files = []
        for field in ("stacks", "masks"):
            for name in order:
                path = folder / f"{field}-{name}.nii.gz"
                write_volume(moved(volumes[field, name], frame), path)
                files.append((field, (path.name, path.read_bytes(), "application/gzip")))
        r = client.post("/v1/predict", files=files, data=fields)
        r.raise_for_status()
        return {name: StackAnswer.of(stack) for name, stack in zip(order, r.json()["stacks"])}

    with tempfile.TemporaryDirectory() as tmp, \
            TestClient(create_app(Settings(data_dir=Path(tmp) / "jobs"), registry=registry)) as client:
        base = ask(client, Path(tmp), np.eye(4), names)
        variants = {label: ask(client, Path(tmp), frame, names) for label, frame in FRAMES.items()}
        if len(names) > 1:
            variants["stacks in reverse order"] = ask(client, Path(tmp), np.eye(4), names[::-1])
    print("per stack, over the slices both answers accept: the median / largest move of a slice's centre (mm), "
          "its largest turn (deg), the slices")
    for label, answer in variants.items():
        worst = [changes(answer[n], base[n]) for n in names]
        print(f"  {label}: " + " | ".join(f"{n} {m:.2f} / {x:.2f} mm, {r:.2f} deg, {k}" for n, (m, x, r, k) in zip(names, worst)))

if __name__ == "__main__":
    main()
