"""Where training time goes on this machine: simulation vs network, in samples/s.

Measures, single-threaded, on the training volumes (or a packed folder):

* ``acquire``: the 3D sampling of clean thick slices (trilinear ``grid_sample`` at 5 PSF points);
* ``corrupt`` and ``preprocess``: the per-use redraw (bias, gamma, voids, Rician noise, mask) and
  the service's slice preprocessing, which a bank of clean slices repeats ``reuse`` times;
* ``network``: one Adam step (forward + backward) of the default network at batch 64, with 1 and 2
  threads, and channels-last;

and prints the simulation rate one worker sustains for several ``reuse`` values, next to the
network's rate: the stream is simulation-bound when ``workers x simulation < network``.

    .venv/bin/python benchmarks/train_bench.py [--root data/packed] [--label-type anchor]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes, split
from model_export.losses import point_loss
from model_export.model import SVRNet
from model_export.simulate import SimulationConfig, SliceSimulator
from model_export.stream import fresh_acquisition
from service.core.machine import cpu_description
from service.geometry import encodings
from service.preprocess.slices import preprocess_slices


def timed(fn, repeats: int) -> float:
    """Median seconds of ``fn()`` over ``repeats`` calls (after one warm-up)."""
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--root", type=Path, default=DEFAULT_ATLAS_ROOT)
    ap.add_argument("--label-type", default="anchor")
    ap.add_argument("--repeats", type=int, default=8)
    args = ap.parse_args()
    print(f"machine: {cpu_description()}")
    torch.set_num_threads(1)
    names = split(args.root)[0][:4]
    sim = SliceSimulator(load_volumes(names, args.root), SimulationConfig())
    rng = np.random.default_rng(0)
    acq = fresh_acquisition(sim, rng)
    n = len(acq.poses)
    t_acq = timed(lambda: fresh_acquisition(sim, rng), args.repeats)
    t_cor = timed(lambda: sim.corrupt(acq.images, acq.masks, rng), args.repeats)
    img, msk = sim.corrupt(acq.images, acq.masks, rng)
    c = sim.config
    t_pre = timed(lambda: preprocess_slices(img, msk, (acq.pixel_mm,) * 2, c.size, c.pixel_mm), args.repeats)
    t_enc = timed(lambda: encodings.encode(args.label_type, acq.poses), args.repeats)
    per_use = t_cor + t_pre + t_enc
    print(f"simulation, 1 thread, per slice (acquisitions of {n}, {acq.images.shape[1]} px):")
    print(f"  acquire (3D sampling, PSF)   {1e3 * t_acq / n:7.2f} ms")
    print(f"  corrupt                      {1e3 * t_cor / n:7.2f} ms")
    print(f"  preprocess (service)         {1e3 * t_pre / n:7.2f} ms")
    print(f"  label encode                 {1e3 * t_enc / n:7.2f} ms")
    for reuse in (1, 3, 6, 12, 24):
        rate = n / (per_use + t_acq / reuse)
        print(f"  one worker, reuse {reuse:2d}: {rate:7.1f} samples/s")

    batch = 64
    x = torch.rand(batch, 1, c.size, c.size) * 255
    y = torch.from_numpy(encodings.encode(args.label_type, np.repeat(acq.poses, 4, 0)[:batch]).astype(np.float32))
    for threads in (1, 2):
        for channels_last in (False, True):
            torch.set_num_threads(threads)
            model = SVRNet(label_type=args.label_type, hidden=128, dropout=0.25, grid_channels=32)
            xx = x
            if channels_last:
                model = model.to(memory_format=torch.channels_last)
                xx = x.contiguous(memory_format=torch.channels_last)
            opt = torch.optim.Adam(model.parameters(), 1e-4)

            def step() -> None:
                loss = point_loss(model(xx), y, model.label_mean, model.label_scale, "min").mean()
                opt.zero_grad()
                loss.backward()
                opt.step()

            t = timed(step, max(3, args.repeats // 2))
            print(f"network step, batch {batch}, {threads} thread(s), channels-last {channels_last!s:5}: "
                  f"{batch / t:7.1f} samples/s")


if __name__ == "__main__":
    main()
