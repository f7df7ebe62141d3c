"""Download a second public real scan for evaluation: ``sub-01`` of the MIAL super-resolution
toolkit's sample data (six whole-uterus T2 HASTE stacks of 320 x 320 x 22, 1.125 mm pixels, 3.3 mm
apart, 1.5 T, each with a manual brain mask drawn to the skull; BSD-3 licence), from a pinned commit
of its public repository.

    .venv/bin/python tools/fetch_real_scan.py [DIR]      # default ../shared/data/extra_scans

It writes ``DIR/mial_sub01/runK.nii.gz`` and ``runK_brain_mask.nii.gz`` (K = 1..6, the layout of
``../shared/data/real_scans``) and the licence. The scan is for evaluation only (never for training
or tuning) and is never committed: the evaluation tools take its folder
(``benchmarks/predict_bench.py --real DIR/mial_sub01``, ``svrnet-train localiser compare/ship
--real-scans DIR``).
"""

from __future__ import annotations

import hashlib
import sys
import urllib.request
from pathlib import Path

REPOSITORY = "https://raw.githubusercontent.com/Medical-Image-Analysis-Laboratory/mialsuperresolutiontoolkit"
COMMIT = "ecd37d5f84189c33a76368d3653d9af588032b3c"
FILES = {
    **{f"run{k}.nii.gz": f"data/sub-01/anat/sub-01_run-{k}_T2w.nii.gz" for k in range(1, 7)},
    **{f"run{k}_brain_mask.nii.gz": f"data/derivatives/manual_masks/sub-01/anat/sub-01_run-{k}_T2w_desc-brain_mask.nii.gz"
       for k in range(1, 7)},
    "LICENSE.txt": "LICENSE.txt",
}
SHA256_PREFIX = {
    "run1.nii.gz": "be83d9c2c6d9b83c", "run2.nii.gz": "5bda15f4cfa03f91", "run3.nii.gz": "7fa77748de4de73c",
    "run4.nii.gz": "6e9d158430468510", "run5.nii.gz": "7a17bd95c0bbaceb", "run6.nii.gz": "5abfe46881e2b3aa",
    "run1_brain_mask.nii.gz": "f5928e6b2ffeb65e", "run2_brain_mask.nii.gz": "2c497fafe960a895",
    "run3_brain_mask.nii.gz": "e4459913c7d8162c", "run4_brain_mask.nii.gz": "43ba053394f21882",
    "run5_brain_mask.nii.gz": "8293ccd3d22aae7b", "run6_brain_mask.nii.gz": "6b73de75b900c9ba",
    "LICENSE.txt": "ea5f5c0b58499843",
}
"""The first 16 hex digits of each file's SHA-256 at :data:`COMMIT`: a download that differs is refused."""
DEFAULT_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "extra_scans"


def fetch(root: Path) -> Path:
    """Download the scan into ``root/mial_sub01`` (files already there are kept); returns that folder."""
    folder = Path(root) / "mial_sub01"
    folder.mkdir(parents=True, exist_ok=True)
    for name, path in FILES.items():
        target = folder / name
        if target.exists():
            continue
        with urllib.request.urlopen(f"{REPOSITORY}/{COMMIT}/{path}", timeout=60) as r:  # noqa: S310 - a fixed https URL
            data = r.read()
        if hashlib.sha256(data).hexdigest()[:16] != SHA256_PREFIX[name]:
            raise SystemExit(f"{name}: the download differs from the pinned file")
        target.with_suffix(".part").write_bytes(data)
        target.with_suffix(".part").rename(target)
        print(f"{target} ({len(data) // 1024} KB)")
    return folder


if __name__ == "__main__":
    fetch(Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT_DIR)
