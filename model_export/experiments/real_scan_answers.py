"""What ``/v1/predict`` answers on the real scans of ``../shared/data/real_scans``: per stack, the
slices accepted of those with a brain and their median ``expected_error_mm``, for the shared scan
without masks, with its manual masks (sent as they are: no ``masks_hold_csf``), each stack alone
with its manual mask, and the stacks of another site without masks (docs/accuracy.md, "Real
scans"). Each row is one request through the app in process (N4, 100 MC samples, every stage, the
default accept flags). A model with fixed draws answers a request again as it did
(docs/training.md, "Export and MC dropout"); ``--repeats`` sends each request again, which checks that.
``--storages DIR`` sends instead the stacks of the scan folder ``DIR`` (each ``NAME.nii.gz`` beside a
manual mask) without masks, every stack stored each of the eight ways a file can hold its in-plane
voxels (either axis reversed, the two swapped; the world unchanged): one row each, which should
all be the same (docs/reports/localiser-experiments.md, "Slices laid out by the scanner's axes").

    .venv/bin/python model_export/experiments/real_scan_answers.py [--repeats 2] [--storages DIR ...]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from fastapi.testclient import TestClient  # noqa: E402

from model_export.experiments.localiser_sweep import STORAGES, stored_as  # noqa: E402
from model_export.localiser.evaluate import MASK_SUFFIX, REAL_SCANS, masked_files  # noqa: E402
from service.io.volume import read_volume, write_volume  # noqa: E402
from service.main import create_app  # noqa: E402

SHARED = ("mial_lausanne_t30", ["axial1_lr", "coronal1_lr", "sagittal1_lr"])
OTHER_SITE = ("bch_f0832s1", ["fetus_03", "fetus_04"])


def files_of(folder: Path, names: list[str], masks: bool) -> list[tuple[str, tuple[str, bytes]]]:
    """The multipart files of a request: the stacks, and their manual masks (``NAME`` + :data:`MASK_SUFFIX`)
    with ``masks``."""
    files = [("stacks", (f"{n}.nii.gz", (folder / f"{n}.nii.gz").read_bytes())) for n in names]
    if masks:
        files += [("masks", (f"{n}.nii.gz", (folder / f"{n}{MASK_SUFFIX}").read_bytes())) for n in names]
    return files


def answer_row(client: TestClient, folder: Path, names: list[str], masks: bool) -> str:
    """One request's stacks: accepted of the slices with a brain (median expected error), and the
    request's frame error (its network error, and what it adds to each slice's expected error)."""
    r = client.post("/v1/predict", files=files_of(folder, names, masks), data={"mc_samples": "100"})
    r.raise_for_status()
    cells = []
    for stack in r.json()["stacks"]:
        brain = [s for s in stack["slices"] if s["reason"] != "empty"]
        expected = np.median([s["expected_error_mm"] for s in brain]) if brain else float("nan")
        cells.append(f"{sum(s['accepted'] for s in brain)} of {len(brain)} ({expected:.1f} mm)")
    frame = r.json()["stacks"][0].get("frame") or {}
    return (", ".join(cells) + f"; frame: network error {frame.get('request_network_error_mm')} mm, "
            f"{frame.get('expected_error_added_mm')} mm added")


def storage_rows(client: TestClient, folder: Path) -> None:
    """Print the answer without masks for every storage of the scan ``folder``'s masked stacks."""
    names = [name for name, _, _ in masked_files(folder)]
    volumes = {n: read_volume(folder / f"{n}.nii.gz") for n in names}
    with tempfile.TemporaryDirectory() as tmp:
        for storage in STORAGES:
            for n in names:
                write_volume(stored_as(volumes[n], *storage), Path(tmp) / f"{n}.nii.gz")
            label = ", ".join(k for k, on in zip(("first reversed", "second reversed", "swapped"), storage)
                              if on) or "as stored"
            print(f"{folder.name}, {label}:", answer_row(client, Path(tmp), names, False), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--storages", type=Path, nargs="+", help="scan folders to send stored every way, without masks")
    args = ap.parse_args()
    if args.storages:
        with TestClient(create_app(), base_url="http://127.0.0.1") as client:
            for folder in args.storages:
                storage_rows(client, folder)
        return
    shared, other = REAL_SCANS / SHARED[0], REAL_SCANS / OTHER_SITE[0]
    if not shared.is_dir():
        sys.exit(f"needs the real scans at {REAL_SCANS}")
    with TestClient(create_app(), base_url="http://127.0.0.1") as client:
        for _ in range(args.repeats):
            print("shared scan, localiser:", answer_row(client, shared, SHARED[1], False), flush=True)
            print("shared scan, manual masks:", answer_row(client, shared, SHARED[1], True), flush=True)
            print("each stack alone, manual mask:",
                  "; ".join(answer_row(client, shared, [n], True) for n in SHARED[1]), flush=True)
            if other.is_dir():
                print("other site, localiser:", answer_row(client, other, OTHER_SITE[1], False), flush=True)


if __name__ == "__main__":
    main()
