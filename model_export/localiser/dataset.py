"""Synthetic localiser data on disk: shards of network-grid slices and brain targets.

Each shard ``<style>-<seed>.npz`` holds one synthetic stack (:func:`~model_export.localiser.scenes.synth_stack`)
passed through the service's own input function: ``slices [n, Hp, Wp]`` float16 (the middle channel
of :func:`~service.preprocess.localiser_inputs.localiser_inputs`; the 2.5D channels are rebuilt with
:func:`~service.preprocess.localiser_inputs.with_neighbours`) and ``target [n, Hp, Wp]`` uint8 (brain
fraction x 255), ``grid_mm`` and ``generator`` (the JSON of the generator's settings: style, grid,
shares, motion, atlas volumes, the code's commit), plus the stack itself when ``keep_stack`` (for evaluation on the stack's own grid)
with ``t2_like`` (held-out stacks alternate T2-like and uniformly random contrasts by seed).
"""

from __future__ import annotations

import json
import os
from multiprocessing import Pool
from pathlib import Path

import numpy as np

from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes
from model_export.localiser import GRID_MM
from model_export.localiser.record import git_state
from model_export.localiser.scenes import HeadModel, synth_stack
from service.preprocess.localiser_inputs import localiser_inputs, target_maps

_HEADS: list[HeadModel] = []


def _init(names: list[str], root: Path) -> None:
    _HEADS.extend(HeadModel.from_arrays(v.image, v.mask, v.affine) for v in load_volumes(names, root))


def _one(job: tuple[Path, str, int, float, bool, float, float, str | None, str]) -> str:
    out, style, seed, grid_mm, keep_stack, shading_share, faint_skull_share, motion, settings = job
    path = out / f"{style}-{seed:06d}.npz"
    if path.exists():
        return path.name
    rng = np.random.default_rng(seed)
    head = _HEADS[int(rng.integers(len(_HEADS)))]
    random_contrast = bool(seed % 2) if style == "heldout" else None      # held out: T2-like and random, alternately
    volume, mask = synth_stack(head, rng, style, random_contrast, shading_share, faint_skull_share, motion)
    x, grid = localiser_inputs(volume, grid_mm)
    extra = {"stack": volume.array.astype(np.float16), "affine": volume.affine, "mask": mask,
             "t2_like": not random_contrast} if keep_stack else {}
    partial = path.with_suffix(".partial")            # a reader beside the generator never sees half a shard
    with open(partial, "wb") as f:
        np.savez_compressed(f, slices=x[:, 1].astype(np.float16), grid_mm=np.float64(grid_mm),
                            generator=np.str_(settings),
                            target=np.round(target_maps(mask, volume, grid) * 255).astype(np.uint8), **extra)
    os.replace(partial, path)
    return path.name


def generate(out: Path, names: list[str], count: int, style: str, grid_mm: float, first_seed: int = 0,
             workers: int = 2, keep_stack: bool = False, root: Path = DEFAULT_ATLAS_ROOT,
             shading_share: float = 0.0, faint_skull_share: float = 0.0, motion: str | None = None) -> list[str]:
    """Write ``count`` shards of ``style`` from the atlas volumes ``names`` (seeds ``first_seed...``),
    ``shading_share`` of them with a dark region over the head, ``faint_skull_share`` of the heads
    with a faint skull, the heads moving as ``motion`` says (default: the generator's own drift)
    (:func:`~model_export.localiser.scenes.synth_scene`). Each shard records these settings
    (``generator``), which a training checkpoint carries on (:mod:`model_export.localiser.record`)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    settings = json.dumps({"style": style, "grid_mm": grid_mm, "shading_share": shading_share,
                           "faint_skull_share": faint_skull_share, "motion": motion, "volumes": sorted(names),
                           "commit": git_state()}, sort_keys=True)
    jobs = [(out, style, first_seed + i, grid_mm, keep_stack, shading_share, faint_skull_share, motion, settings)
            for i in range(count)]
    with Pool(workers, initializer=_init, initargs=(names, root)) as pool:
        return list(pool.imap_unordered(_one, jobs))


def main(argv: list[str] | None = None) -> list[str]:
    """``python -m model_export.localiser.dataset``: :func:`generate` of training shards without typer,
    for a bare GPU host that generates its shards beside the training; ``--root`` may be a packed
    folder of the training volumes alone (``svrnet-train pack --training-only``).

    Example:
        python -m model_export.localiser.dataset --out SHARDS --root data/packed_loc --count 2000 --seed 7000000 \\
            --workers 10 --faint-skull-share 0.25
    """
    import argparse

    from model_export.atlas import training_volumes
    from model_export.localiser.scenes import MOTIONS

    ap = argparse.ArgumentParser(prog="python -m model_export.localiser.dataset", description=main.__doc__)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--root", type=Path, default=DEFAULT_ATLAS_ROOT)
    ap.add_argument("--count", type=int, default=600)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--grid-mm", type=float, default=GRID_MM)
    ap.add_argument("--shading-share", type=float, default=0.0)
    ap.add_argument("--faint-skull-share", type=float, default=0.0)
    ap.add_argument("--motion", choices=MOTIONS)
    args = ap.parse_args(argv)
    return generate(args.out, training_volumes(args.root), args.count, "train", args.grid_mm, args.seed, args.workers,
                    root=args.root, shading_share=args.shading_share, faint_skull_share=args.faint_skull_share,
                    motion=args.motion)


if __name__ == "__main__":              # run as the module itself, so its worker processes can find its functions
    from model_export.localiser.dataset import main as module_main

    module_main()
