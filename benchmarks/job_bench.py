"""``POST /v1/reconstructions`` end to end over real HTTP: a whole job's wall time and when each
stage began, on a real scan with and without its masks, and the ratio to another revision in the
same run.

The job is what a user gets from ``svrnet reconstruct --wait``: the stacks (and masks) uploaded, the
poses predicted, the never-worse paths at 1.5 mm, the volume at 0.8 mm, the atlas-frame and midline
steps, the outputs written. The stage times are when the job's ``stage`` first read so, polled every
0.2 s (a stage shorter than that may not show); the peak memory is the largest resident set of the
server and its worker processes together seen at those polls, as their proportional set sizes
(a page that processes share counted once in all; target <= 2 GB).

    .venv/bin/python benchmarks/job_bench.py ../shared/data/real_scans/mial_lausanne_t30 [--baseline REV]
        [--resolution MM] [--with-masks-only]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import httpx
import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from client.job_views import refined_poses_line  # noqa: E402
from model_export.localiser.evaluate import masked_files  # noqa: E402
from predict_bench import revision_tree, served, wait_ready  # noqa: E402
from service.core.machine import cpu_description  # noqa: E402

FINAL = ("succeeded", "failed", "cancelled")


def tree_rss_mb(pid: int) -> float:
    """The memory of process ``pid`` and all its descendants (MB): the sum of their proportional set
    sizes, so that a page a forked worker shares with the server counts once."""
    try:
        root = psutil.Process(pid)
        procs = [root, *root.children(recursive=True)]
    except psutil.NoSuchProcess:
        return 0.0
    total = 0
    for p in procs:
        try:
            total += p.memory_full_info().pss
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            pass
    return total / 2**20


def run_job(client: httpx.Client, files: list[tuple[Path, Path]], masks: bool, server_pid: int,
            resolution_mm: float = 0.8) -> tuple[float, str, dict[str, float], dict[str, float], dict]:
    """One job: its wall time from upload to a final status, that status, when each stage began (s),
    the peak memory of the server's process tree during each stage (MB), and its report (or, for a
    job that failed, its error)."""
    upload = [("stacks", (s.name, s.read_bytes())) for s, _ in files]
    upload += [("masks", (m.name, m.read_bytes())) for _, m in files] if masks else []
    t0 = time.perf_counter()
    r = client.post("/v1/reconstructions", files=upload, data={"masks_hold_csf": "true" if masks else "false",
                                                               "resolution_mm": str(resolution_mm)})
    r.raise_for_status()
    job = r.json()["job_id"]
    began: dict[str, float] = {}
    peak: dict[str, float] = {}
    while True:
        st = client.get(f"/v1/reconstructions/{job}").json()
        stage = str(st.get("stage"))
        began.setdefault(stage, time.perf_counter() - t0)
        peak[stage] = max(peak.get(stage, 0.0), tree_rss_mb(server_pid))
        if st["status"] in FINAL:
            return time.perf_counter() - t0, st["status"], began, peak, st.get("report") or {"error": st.get("error")}
        time.sleep(0.2)


def measure(root: Path, files: list[tuple[Path, Path]], kinds: tuple[bool, ...] = (True, False),
            resolution_mm: float = 0.8) -> dict[bool, tuple[float, str, dict[str, float], dict[str, float], dict]]:
    """A job with the masks and one without (``kinds``), on a server of the code under ``root`` and its
    models."""
    with served(root, root / "service" / "models") as (server, port):
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=300) as client:
            wait_ready(client)
            return {masks: run_job(client, files, masks, server.pid, resolution_mm) for masks in kinds}


def durations(began: dict[str, float], total: float) -> dict[str, float]:
    """Each stage's seconds: from when it began to when the next one did."""
    names = list(began)
    ends = [began[n] for n in names[1:]] + [total]
    return {n: end - began[n] for n, end in zip(names, ends)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scan", type=Path, help="a real scan's folder: NAME.nii.gz beside NAME_brain_mask.nii.gz")
    ap.add_argument("--baseline", help="a git revision to compare with, in the same run")
    ap.add_argument("--resolution", type=float, default=0.8, help="the volume's voxel size, mm (resolution_mm)")
    ap.add_argument("--with-masks-only", action="store_true", help="only the job given the masks")
    args = ap.parse_args()
    kinds = (True,) if args.with_masks_only else (True, False)
    print(f"machine: {cpu_description()}")
    files = [(stack, mask) for _, stack, mask in masked_files(args.scan)]
    if not files:
        sys.exit(f"{args.scan}: no stack with a *_brain_mask.nii.gz beside it")
    now = measure(ROOT, files, kinds, args.resolution)
    before = None
    if args.baseline:
        with revision_tree(args.baseline) as tree:
            before = measure(tree, files, kinds, args.resolution)
    for masks in kinds:
        wall, status, began, peak, report = now[masks]
        ratio = f"; {before[masks][0]:.1f} s at {args.baseline} (x{wall / before[masks][0]:.2f})" if before else ""
        print(f"{len(files)} stacks of {args.scan.name} {'with their masks' if masks else 'without masks'} at "
              f"{args.resolution} mm: "
              f"{status} in {wall:.1f} s{ratio}; peak memory of the server and its workers "
              f"{max(peak.values()):.0f} MB; left-out slices placed by their stack's motion "
              f"{report.get('left_out_placed_by_stack_motion')}, by the volume "
              f"{report.get('left_out_placed_by_volume')}")
        if report.get("error"):
            print(f"   {report['error']}")
        if report.get("refined_poses"):
            print(f"   {refined_poses_line(report['refined_poses'])}")
        longest = sorted(durations(began, wall).items(), key=lambda kv: -kv[1])[:6]
        print("   longest stages, s: " + ", ".join(f"{k} {v:.1f}" for k, v in longest))
        if before:
            old = durations(before[masks][2], before[masks][0])
            print("   the same at the baseline: " + ", ".join(f"{k} {old.get(k, float('nan')):.1f}" for k, _ in longest))
        largest = sorted(peak.items(), key=lambda kv: -kv[1])[:4]
        print("   largest memory, MB: " + ", ".join(f"{k} {v:.0f}" for k, v in largest))
        if before:
            old_peak = before[masks][3]
            print(f"   the same at the baseline (peak {max(old_peak.values()):.0f} MB): "
                  + ", ".join(f"{k} {old_peak.get(k, float('nan')):.0f}" for k, _ in largest))


if __name__ == "__main__":
    main()
