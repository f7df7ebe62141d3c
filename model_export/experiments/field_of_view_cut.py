"""What a field of view that cuts the brain in the plane of one stack's slices does to a real request.

The real scan (``mial_lausanne_t30``, three stacks) runs through ``/v1/predict``'s pipeline (every
stage on), as sent, then with one stack's field of view ending inside the brain: its voxels (and
its mask) kept up to a share of the brain's extent along the stack's first voxel axis, as a
scanner whose field of view was planned too tight, or a fetus that moved out of it, writes them;
and with that stack left out of the request. For each variant and stack it prints the slices
accepted, and how far the accepted slices' poses lie from the uncut request's answer (median and
largest E.D.). The cut stack's slices keep their voxel indices (the cut starts at index 0), so
the answers compare slice by slice. ``--without-masks``: every stack localised by the service.

    .venv/bin/python model_export/experiments/field_of_view_cut.py [--stack 0] [--shares 0.9,0.85,0.75,0.6] [--without-masks]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.localiser.evaluate import REAL_SCANS, masked_files  # noqa: E402
from model_export.localiser.pose_accuracy import pose_estimator  # noqa: E402
from model_export.localiser.pose_accuracy import slice_poses  # noqa: E402
from service.geometry import anchors  # noqa: E402
from service.io.volume import Volume, read_volume  # noqa: E402
from service.pipeline.documents import stack_objects  # noqa: E402
from service.pipeline.predict import predict  # noqa: E402
from service.pipeline.prepare import PreparedStack, StackUpload, prepare_stacks  # noqa: E402
from service.preprocess.stack import mask_box  # noqa: E402

Stack = tuple[str, Volume, Volume]


def cut(volume: Volume, mask: Volume, share: float) -> tuple[Volume, Volume]:
    """``volume`` and ``mask`` ending (along the first voxel axis) ``share`` of the way through the brain."""
    box = mask_box(mask.array > 0, [0, 0, 0])[0]
    end = int(box.start + (box.stop - box.start) * share)
    keep = (slice(0, end), slice(None), slice(None))
    return volume.region(keep), mask.region(keep)


def compare(base: list[dict], got: dict[str, dict], prepared: dict[str, PreparedStack]) -> list[str]:
    """Per stack of ``base`` (the uncut answer): accepted slices in ``got`` and their poses' E.D. from
    the uncut answer's (median / largest); ``left out`` where ``got`` has no such stack."""
    rows = []
    for stack in base:
        name = stack["filename"]
        if name not in got:
            rows.append(f"{name}: left out")
            continue
        (pa, _), (pb, _) = slice_poses(stack, prepared[name]), slice_poses(got[name], prepared[name])
        accepted = np.array([s["accepted"] for s in got[name]["slices"]])
        ed = anchors.ed(pa[accepted], pb[accepted])
        far = f"{np.median(ed):.1f} / {ed.max():.1f} mm" if accepted.any() else "-"
        rows.append(f"{name}: accepted {accepted.sum()}/{len(accepted)}, {far}")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scan", type=Path, default=REAL_SCANS / "mial_lausanne_t30")
    ap.add_argument("--stack", type=int, default=0, help="which stack's field of view is cut (file order)")
    ap.add_argument("--shares", default="0.9,0.85,0.75,0.6", help="where the cut ends, as shares of the brain")
    ap.add_argument("--without-masks", action="store_true", help="every stack localised by the service")
    args = ap.parse_args()
    files = masked_files(args.scan)
    if not files:
        sys.exit(f"needs stacks with manual masks in {args.scan}")
    estimator = pose_estimator()
    stacks: list[Stack] = [(name, read_volume(s), read_volume(m)) for name, s, m in files]

    def answer(request: list[Stack]) -> tuple[dict[str, dict], dict[str, PreparedStack]]:
        uploads = [StackUpload(name, v, None if args.without_masks else m) for name, v, m in request]
        prepared = prepare_stacks(uploads, estimator.info, True, workers=2)
        objects = stack_objects(predict(prepared, estimator, 100, estimator.info.variance_threshold)[0])
        return {o["filename"]: o for o in objects}, {p.upload.filename: p for p in prepared}

    base, prepared = answer(stacks)
    base_list = [base[name] for name, _, _ in stacks]
    print("as sent:", "; ".join(compare(base_list, base, prepared)), flush=True)
    name, volume, mask = stacks[args.stack]
    for share in (float(s) for s in args.shares.split(",")):
        request = list(stacks)
        request[args.stack] = (name, *cut(volume, mask, share))
        print(f"{name} cut at {share:.2f} of the brain:", "; ".join(compare(base_list, answer(request)[0], prepared)),
              flush=True)
    rest = [s for k, s in enumerate(stacks) if k != args.stack]
    print(f"{name} left out:", "; ".join(compare(base_list, answer(rest)[0], prepared)), flush=True)


if __name__ == "__main__":
    main()
