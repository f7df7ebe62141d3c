"""Download public real scans for evaluation, from pinned commits of their public repositories.

* ``mial_sub01``: ``sub-01`` of the MIAL super-resolution toolkit's sample data (six whole-uterus
  T2 HASTE stacks of 320 x 320 x 22, 1.125 mm pixels, 3.3 mm apart, 1.5 T, each with a manual brain
  mask drawn to the skull; BSD-3 licence).
* ``bch_fetus40`` (``--scan bch_fetus40``): ``fetus_40`` of the "challenging" test set of Boston
  Children's Hospital's fetal brain extraction (one whole-uterus T2 stack of 256 x 256 x 30, 1.17
  mm pixels, 3 mm slices, with its manual brain mask; the group of `bch_f0832s1`). Its repository has no licence
  file: it is fetched to evaluate on your own machine, and never redistributed.

    .venv/bin/python tools/fetch_real_scan.py [DIR] [--scan NAME]      # default ../shared/data/extra_scans, mial_sub01

It writes ``DIR/<scan>/<stack>.nii.gz`` and ``<stack>_brain_mask.nii.gz`` (the layout of
``../shared/data/real_scans``; an uncompressed file is gzipped) and the licence where there is one.
A scan is for evaluation only (never for training or tuning) and is never committed: the
evaluation tools take its folder (``benchmarks/predict_bench.py --real DIR/mial_sub01``,
``svrnet-train localiser compare/ship --real-scans DIR``).
"""

from __future__ import annotations

import argparse
import gzip
import hashlib
import urllib.error
import urllib.request
from pathlib import Path

RAW = "https://raw.githubusercontent.com"
SCANS = {
    "mial_sub01": {
        "repository": "Medical-Image-Analysis-Laboratory/mialsuperresolutiontoolkit",
        "commit": "ecd37d5f84189c33a76368d3653d9af588032b3c",
        "files": {
            **{f"run{k}.nii.gz": f"data/sub-01/anat/sub-01_run-{k}_T2w.nii.gz" for k in range(1, 7)},
            **{f"run{k}_brain_mask.nii.gz":
               f"data/derivatives/manual_masks/sub-01/anat/sub-01_run-{k}_T2w_desc-brain_mask.nii.gz"
               for k in range(1, 7)},
            "LICENSE.txt": "LICENSE.txt",
        },
        "sha256": {
            "run1.nii.gz": "be83d9c2c6d9b83c", "run2.nii.gz": "5bda15f4cfa03f91", "run3.nii.gz": "7fa77748de4de73c",
            "run4.nii.gz": "6e9d158430468510", "run5.nii.gz": "7a17bd95c0bbaceb", "run6.nii.gz": "5abfe46881e2b3aa",
            "run1_brain_mask.nii.gz": "f5928e6b2ffeb65e", "run2_brain_mask.nii.gz": "2c497fafe960a895",
            "run3_brain_mask.nii.gz": "e4459913c7d8162c", "run4_brain_mask.nii.gz": "43ba053394f21882",
            "run5_brain_mask.nii.gz": "8293ccd3d22aae7b", "run6_brain_mask.nii.gz": "6b73de75b900c9ba",
            "LICENSE.txt": "ea5f5c0b58499843",
        },
    },
    "bch_fetus40": {
        "repository": "bchimagine/fetal-brain-extraction_t2w",
        "commit": "54a73dc649a377651787ed48ec0494a98f165303",
        "files": {
            "fetus_40.nii.gz": "data/test_challenging/Challenging/fetus_40.nii",
            "fetus_40_brain_mask.nii.gz": "data/test_challenging/Challenging/goodmask/maskfetus_40.nii",
        },
        "sha256": {"fetus_40.nii.gz": "bde34c6b2ddc0b02", "fetus_40_brain_mask.nii.gz": "7317f5051c39b774"},
    },
}
"""Each scan's repository, commit, files (the name written -> the path there) and the first 16 hex
digits of each file's SHA-256 as downloaded: a download that differs is refused."""
DEFAULT_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "extra_scans"


def _fetch_file(spec: dict, name: str, path: str, target: Path) -> None:
    """One file of a scan into ``target`` (kept where it is there already), checked against its pin."""
    if target.exists():
        return
    url = f"{RAW}/{spec['repository']}/{spec['commit']}/{path}"
    try:
        with urllib.request.urlopen(url, timeout=60) as r:  # noqa: S310 - a fixed https URL
            data = r.read()
    except OSError as e:                                    # URLError is one
        reason = getattr(e, "reason", None) or e
        raise SystemExit(f"{name}: could not be downloaded from {RAW.split('//')[1]} ({reason}); "
                         "a machine with access to GitHub can fetch it, then copy the folder") from None
    if hashlib.sha256(data).hexdigest()[:16] != spec["sha256"][name]:
        raise SystemExit(f"{name}: the download differs from the pinned file")
    if name.endswith(".gz") and not path.endswith(".gz"):
        data = gzip.compress(data, mtime=0)
    target.with_suffix(".part").write_bytes(data)
    target.with_suffix(".part").rename(target)
    print(f"{target} ({len(data) // 1024} KB)")


def fetch(root: Path, scan: str = "mial_sub01") -> Path:
    """Download ``scan`` into ``root/<scan>`` (files already there are kept); returns that folder.
    :class:`SystemExit` names a file that could not be downloaded (no network, the host not
    answering); the folders this call made are removed where they are still empty."""
    spec = SCANS[scan]
    folder = Path(root) / scan
    made = [p for p in (folder, *folder.parents) if not p.exists()]      # the folders this call makes
    folder.mkdir(parents=True, exist_ok=True)
    try:
        for name, path in spec["files"].items():
            _fetch_file(spec, name, path, folder / name)
    except BaseException:                     # no download, one that differs, an interrupt: no empty folders left
        for made_folder in made:                                           # innermost first, while empty
            if not any(made_folder.iterdir()):
                made_folder.rmdir()
        raise
    return folder


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", nargs="?", type=Path, default=DEFAULT_DIR)
    ap.add_argument("--scan", choices=sorted(SCANS), default="mial_sub01")
    args = ap.parse_args()
    fetch(args.dir, args.scan)
