"""Whether `/v1/predict`'s poses depend on how a scan's files place and store it, or on the order of its stacks.

A file's scanner frame is the scanner's choice (its isocentre, the table position, the patient's
position on the table), and so is the order it stores the voxels in (slices first to last or last
to first, rows up or down); neither is the fetus's. Moving or turning every stack of a request by
one rigid map of scanner mm changes nothing the network sees, so each slice's map from scanner to
atlas should move with the frame and nothing else; nor should sending the same stacks in another
order change anything. Storing a stack's voxels in another order shows the network the same slices
(mirrored where rows are reversed: the network's own symmetry, not the stages', is then tested),
and should change no slice's place in the atlas beyond that.

This script sends a real scan's stacks (with their manual masks) to the app as they are and in
each variant (:data:`FRAMES`, :data:`STORAGE`, reversed order), and prints per variant and per
stack how the slices both answers accept (with the stages off: those with brain) moved from the
answer to the files as they are: the
median and largest move of a slice's centre (mm), the largest turn (degrees). Form fields after
the stack names (``image_consistency=false stack_consistency=false``) switch stages off, to find
the stage that depends on the variant.

    .venv/bin/python model_export/experiments/scanner_frame.py ../shared/data/real_scans/mial_lausanne_t30 \\
        axial1_lr[,coronal1_lr,...] [FIELD=VALUE ...]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from fastapi.testclient import TestClient  # noqa: E402

from service.core.settings import Settings  # noqa: E402
from service.geometry import se3  # noqa: E402
from service.geometry.pose import index_reversal, make_pose, translate  # noqa: E402
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
STORAGE = {"slices stored last to first": ("flip", -1), "rows stored the other way": ("flip", 1),
           "in-plane axes swapped": ("swap", None)}
"""Each variant's voxel order: ``flip`` reverses the stack's slice axis (-1) or its first in-plane
axis; ``swap`` exchanges its two in-plane axes."""
MASK_SUFFIX = "_brain_mask.nii.gz"
IN_PLANE_MM = 30.0
"""A slice's turn is seen at points this far from its centre in its plane."""


def moved(volume: Volume, moved_from_scanner: np.ndarray) -> Volume:
    """``volume`` with its scanner frame moved: each voxel lands at ``moved_from_scanner`` of where it was.

    Example:
        >>> v = moved(Volume(np.zeros((2, 2, 2), np.float32), np.diag([2.0, 2.0, 3.0, 1.0])), translate([5.0, 0.0, 0.0]))
        >>> (v.affine @ [1.0, 1.0, 1.0, 1.0]).tolist()
        [7.0, 2.0, 3.0, 1.0]
    """
    return Volume(volume.array, np.asarray(moved_from_scanner, np.float64) @ volume.affine)


def restored(volume: Volume, how: str, which: int | None, slice_axis: int) -> Volume:
    """``volume`` with its voxels stored in another order (:data:`STORAGE`), each still where it was.

    Example (the slice axis reversed: the first voxel is the old last slice's, at the same place):
        >>> v = Volume(np.arange(8, dtype=np.float32).reshape(2, 2, 2), np.diag([1.0, 1.0, 3.0, 1.0]))
        >>> r = restored(v, "flip", -1, 2)
        >>> float(r.array[0, 0, 0]), (r.affine @ [0.0, 0.0, 0.0, 1.0]).tolist()
        (1.0, [0.0, 0.0, 3.0, 1.0])
        >>> s = restored(Volume(v.array, np.diag([1.0, 2.0, 3.0, 1.0])), "swap", None, 2)   # voxel (1, 0, 1) was (0, 1, 1)
        >>> float(s.array[1, 0, 1]), (s.affine @ [1.0, 0.0, 1.0, 1.0]).tolist()
        (3.0, [0.0, 2.0, 3.0, 1.0])
    """
    plane = [a for a in range(3) if a != slice_axis]
    if how == "flip":
        axis = slice_axis if which == -1 else plane[0]
        array = np.flip(volume.array, axis)
        old_from_new = index_reversal(axis, volume.array.shape[axis])
    else:
        order = [0, 1, 2]
        order[plane[0]], order[plane[1]] = plane[1], plane[0]
        array = np.transpose(volume.array, order)
        old_from_new = np.eye(4)[[*order, 3]]                            # a swap: its own inverse
    return Volume(np.ascontiguousarray(array), volume.affine @ old_from_new)


@dataclass
class StackAnswer:
    """What an answer says of one stack's slices: each slice's map scanner -> atlas, where the slice's
    centre is in the scanner, its in-plane axes there, and whether it is accepted."""

    atlas_from_scanner: np.ndarray   # [n, 4, 4]
    centres: np.ndarray              # [n, 3] scanner mm, the voxel grid's centre in the slice's plane
    in_plane: np.ndarray             # [n, 2, 3] unit in-plane axes, scanner
    accepted: np.ndarray             # [n] bool
    with_brain: np.ndarray           # [n] bool: not ``empty``

    @classmethod
    def of(cls, stack: dict) -> "StackAnswer":
        """From one stack of a ``/v1/predict`` answer."""
        poses = np.array([s["atlas_from_voxel"] for s in stack["slices"]])
        affine = np.array(stack["scanner_from_voxel"])
        axis = stack["slice_axis"]
        voxels = np.tile(np.append((np.array(stack["shape"]) - 1) / 2.0, 1.0), (len(poses), 1))
        voxels[:, axis] = [s["index"] for s in stack["slices"]]
        axes = affine[:3, [a for a in range(3) if a != axis]].T
        return cls(poses @ np.linalg.inv(affine), (voxels @ affine.T)[:, :3],
                   np.repeat((axes / np.linalg.norm(axes, axis=1, keepdims=True))[None], len(poses), 0),
                   np.array([s["accepted"] for s in stack["slices"]], bool),
                   np.array([s["reason"] != "empty" for s in stack["slices"]], bool))


def changes(answer: StackAnswer, base: StackAnswer, moved_from_scanner: np.ndarray | None = None,
            ) -> tuple[float, float, float, int]:
    """How one stack's slices moved in the atlas between two answers (``answer`` given the files
    moved by ``moved_from_scanner``), over the slices both accept: the median and largest move of a
    slice's centre (mm), the largest move of points :data:`IN_PLANE_MM` from it in its plane over
    that distance, less the centre's, as an angle (degrees), and how many slices that is (where the
    two answers accept none in common, as with the stages off, the slices with brain). Slices are
    matched by where their centres are.

    Example (one slice moved 0.5 mm and turned 2 deg about the slice normal):
        >>> base = StackAnswer(np.eye(4)[None], np.zeros((1, 3)), np.eye(3)[None, :2], np.array([True]), np.array([True]))
        >>> turned = make_pose(se3.so3_exp(np.radians([0.0, 0.0, 2.0])), [0.0, 0.5, 0.0])
        >>> answer = StackAnswer(turned[None], base.centres, base.in_plane, base.accepted, base.with_brain)
        >>> median, largest, turn, slices = changes(answer, base)
        >>> round(median, 3), round(turn, 3), slices
        (0.5, 2.0, 1)
    """
    m = np.eye(4) if moved_from_scanner is None else np.asarray(moved_from_scanner, np.float64)
    here = (base.centres @ m[:3, :3].T) + m[:3, 3]
    match = np.argmin(np.linalg.norm(answer.centres[None] - here[:, None], axis=2), axis=1)
    both = base.accepted & answer.accepted[match]
    if not both.any():                  # the stages off: nothing is accepted, every slice with brain counts
        both = base.with_brain & answer.with_brain[match]
    if not both.any():
        return float("nan"), float("nan"), float("nan"), 0
    points = base.centres[:, None] + IN_PLANE_MM * np.concatenate([np.zeros_like(base.in_plane[:, :1]), base.in_plane], 1)
    homogeneous = np.concatenate([points, np.ones(points.shape[:2] + (1,))], axis=2)      # [n, 3, 4]
    before = np.einsum("nij,nkj->nki", base.atlas_from_scanner, homogeneous)[..., :3]
    after = np.einsum("nij,nkj->nki", answer.atlas_from_scanner[match] @ m, homogeneous)[..., :3]
    delta = (after - before)[both]                                                         # [b, 3, 3]
    centre = np.linalg.norm(delta[:, 0], axis=1)
    turned = np.linalg.norm(delta[:, 1:] - delta[:, :1], axis=2).max(axis=1)             # the turn's chord
    turn = np.degrees(2.0 * np.arcsin(np.clip(turned / (2.0 * IN_PLANE_MM), 0.0, 1.0)))
    return float(np.median(centre)), float(centre.max()), float(turn.max()), int(both.sum())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scan", type=Path, help="a real scan's folder: NAME.nii.gz beside its manual mask")
    ap.add_argument("names", help="the stacks' names, comma-separated")
    ap.add_argument("fields", nargs="*", metavar="FIELD=VALUE", help="form fields, e.g. image_consistency=false")
    args = ap.parse_args()
    scan, names = args.scan, args.names.split(",")
    fields = {"mc_samples": "30", **dict(arg.split("=", 1) for arg in args.fields)}
    volumes = {(field, name): read_volume(scan / f"{name}{suffix}")
               for field, suffix in (("stacks", ".nii.gz"), ("masks", MASK_SUFFIX)) for name in names}
    axes = {name: int(np.argmax(volumes["stacks", name].spacing)) for name in names}
    registry = ModelRegistry.from_directory(Path(__file__).resolve().parents[2] / "service" / "models")

    def ask(client: TestClient, folder: Path, order: list[str], change) -> dict[str, StackAnswer]:   # noqa: ANN001
        files = []
        for field in ("stacks", "masks"):
            for name in order:
                path = folder / f"{field}-{name}.nii.gz"
                write_volume(change(volumes[field, name], axes[name]), path)
                files.append((field, (path.name, path.read_bytes(), "application/gzip")))
        r = client.post("/v1/predict", files=files, data=fields)
        r.raise_for_status()
        return {name: StackAnswer.of(stack) for name, stack in zip(order, r.json()["stacks"])}

    with tempfile.TemporaryDirectory() as tmp, \
            TestClient(create_app(Settings(data_dir=Path(tmp) / "jobs"), registry=registry), base_url="http://127.0.0.1") as client:
        folder = Path(tmp)
        base = ask(client, folder, names, lambda v, _: v)
        variants = {label: (ask(client, folder, names, lambda v, _, f=frame: moved(v, f)), frame)
                    for label, frame in FRAMES.items()}
        variants |= {label: (ask(client, folder, names, lambda v, a, s=how: restored(v, *s, a)), None)
                     for label, how in STORAGE.items()}
        if len(names) > 1:
            variants["stacks in reverse order"] = (ask(client, folder, names[::-1], lambda v, _: v), None)
    print("per stack, over the slices both answers accept: the median / largest move of a slice's centre (mm), "
          "its largest turn (deg), the slices")
    for label, (answer, frame) in variants.items():
        worst = [changes(answer[n], base[n], frame) for n in names]
        print(f"  {label}: " + " | ".join(f"{n} {m:.2f} / {x:.2f} mm, {r:.2f} deg, {k}" for n, (m, x, r, k) in zip(names, worst)))


if __name__ == "__main__":
    main()
