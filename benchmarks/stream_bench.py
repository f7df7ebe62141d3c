"""``/v1/stream`` over a real WebSocket: pose latency, final poses against ``/v1/predict`` and the
truth, and 32 sessions at once beside ``/v1/predict``.

A uvicorn server with the shipped models runs on 127.0.0.1. Acquisitions are simulated from the
validation volumes (``model_export.acquisitions``; three orthogonal stacks of 128 x 128 slices of
1 mm, 3 mm thick, interleaved) at each motion level and sent slice by slice in their acquisition
order, each slice with its mask, MC-100, N4 on:

1. **latency**: the server's ``latency_ms`` of every pose and the round trip the client sees (the
   next slice goes once the pose is back);
   then whole-uterus stacks (the localiser's held-out scene generator) without masks, so the
   localiser finds the brain slice by slice;
2. **final poses**: the session's last word on each slice (its stack's ``stack`` message and the
   ``update`` messages after it) against the simulated truth (E.D., truth and twin-min) and against
   ``POST /v1/predict`` of the same files, told the same acquisition order (and that answer against
   a second ``/v1/predict`` of the same files: the MC draw's own spread);
3. **load**: ``--sessions`` sessions (threads) streaming at ``--pace`` s a slice while
   ``/v1/predict`` answers 3 stacks of 128 x 128; its wall time against the idle server's.

    .venv/bin/python benchmarks/stream_bench.py [--levels mild,moderate,jumps] [--per-level 2] [--sessions 32]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from websockets.sync.client import connect

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from client import SVRnetClient  # noqa: E402
from model_export.acquisitions import SimulatedStack, simulate_acquisition  # noqa: E402
from model_export.atlas import load_volumes, validation_volumes  # noqa: E402
from model_export.experiments.immediate_poses import ed, network_frame  # noqa: E402
from model_export.localiser.scenes import HeadModel, synth_stack  # noqa: E402
from service.core.machine import cpu_description  # noqa: E402
from service.geometry.pose import translate  # noqa: E402
from service.inference.model_file import load_model  # noqa: E402
from service.io.volume import Volume, write_volume  # noqa: E402
from tests.support.live_server import Server  # noqa: E402


def sent_slices(volume: Volume, mask: np.ndarray | None, order: np.ndarray, name: str) -> list[tuple[dict, list[bytes]]]:
    """A stack's slices (slice axis last) in acquisition ``order`` as stream messages and their
    frames, each with its mask frame unless ``mask`` is None."""
    out = []
    for k in order:
        pixels = np.asarray(volume.array[:, :, k], "<f4")
        msg = {"type": "slice", "stack": name, "index": int(k), "shape": list(pixels.shape), "dtype": "float32",
               "scanner_from_voxel": (volume.affine @ translate([0, 0, int(k)])).tolist(), "mask": mask is not None}
        out.append((msg, [pixels.tobytes()] + ([] if mask is None else [np.asarray(mask[:, :, k], np.uint8).tobytes()])))
    return out


def acquired(stack: SimulatedStack) -> list[tuple[dict, list[bytes]]]:
    return sent_slices(stack.volume, stack.mask.array, np.argsort(stack.times), stack.orientation)


def stream(url: str, stacks: list[list[tuple[dict, list[bytes]]]], pace: float = 0.0, mc: int = 100) -> dict:
    """One session: every slice, then its stack's end; the poses, their round trips, the last word on each slice."""
    rtt, server, last, errors = [], [], {}, []
    with connect(url.replace("http", "ws") + "/v1/stream", max_size=2**26) as ws:
        ws.send(json.dumps({"type": "start", "mc_samples": mc}))
        json.loads(ws.recv())

        def until(kind: str) -> dict:
            while True:
                msg = json.loads(ws.recv())
                for s in msg.get("slices", []) if msg["type"] in ("update", "stack") else []:
                    last[(s["stack"], s["index"])] = s
                if msg["type"] == "error":
                    errors.append(msg["detail"])
                if msg["type"] in (kind, "error"):
                    return msg

        for slices in stacks:
            for msg, frames in slices:
                t = time.perf_counter()
                ws.send(json.dumps(msg))
                for f in frames:
                    ws.send(f)
                pose = until("pose")
                rtt.append((time.perf_counter() - t) * 1e3)
                server.append(pose.get("latency_ms", np.nan))
                last.setdefault((pose.get("stack"), pose.get("index")), pose)
                time.sleep(max(0.0, pace - rtt[-1] / 1e3))
            ws.send(json.dumps({"type": "end_stack", "stack": slices[0][0]["stack"]}))
            until("stack")
        ws.send(json.dumps({"type": "end"}))
        summary = until("summary")
    return {"rtt": rtt, "server": server, "last": last, "errors": errors, "summary": summary}


def accuracy(levels: list[str], per_level: int, server: Server, plane_x: float, volumes: list,
             rng: np.random.Generator) -> None:
    print("\n## Final poses (mean E.D. mm; truth / twin-min) and pose latency, 128 x 128 with masks, MC-100")
    print("| motion | stream | /v1/predict (same order) | stream vs predict | predict vs predict again (0: one answer) "
          "| pose p50 / p95 server | round trip p95 |")
    print("|---|---|---|---|---|---|---|")
    for level in levels:
        rows = {"stream": [], "stream_twin": [], "predict": [], "predict_twin": [], "between": [], "again": []}
        lat = {"server": [], "rtt": []}
        for i in range(per_level):
            vol = volumes[(i + levels.index(level)) % len(volumes)]
            stacks = simulate_acquisition(vol.image, vol.mask, vol.affine, rng, level)
            names = [f"{s.orientation}" for s in stacks]
            got = stream(server.url, [acquired(s) for s in stacks])
            lat["server"] += got["server"]
            lat["rtt"] += got["rtt"]
            with tempfile.TemporaryDirectory() as tmp:
                files, masks = [], []
                for s, n in zip(stacks, names):
                    files.append(Path(tmp) / f"{n}.nii.gz")
                    masks.append(Path(tmp) / f"{n}_mask.nii.gz")
                    write_volume(s.volume, files[-1])
                    write_volume(Volume(s.mask.array, s.mask.affine), masks[-1])
                order = [",".join(str(int(k)) for k in np.argsort(s.times)) for s in stacks]
                with SVRnetClient(server.url, timeout=600) as svr:
                    body = svr.predict(files, masks, slice_order=order)
                    again = svr.predict(files, masks, slice_order=order)       # the MC draw's own spread
            for s, n, st, st2 in zip(stacks, names, body["stacks"], again["stacks"]):
                for k in range(s.volume.array.shape[2]):
                    frame = network_frame(s, k)
                    truth = s.atlas_from_voxel[k] @ translate([0, 0, k])
                    mine = np.array(got["last"][(n, k)]["atlas_from_voxel"])
                    theirs = np.array(st["slices"][k]["atlas_from_voxel"]) @ translate([0, 0, k])
                    twice = np.array(st2["slices"][k]["atlas_from_voxel"]) @ translate([0, 0, k])
                    rows["stream"].append(ed(mine, truth, frame, plane_x))
                    rows["stream_twin"].append(ed(mine, truth, frame, plane_x, True))
                    rows["predict"].append(ed(theirs, truth, frame, plane_x))
                    rows["predict_twin"].append(ed(theirs, truth, frame, plane_x, True))
                    rows["between"].append(ed(mine, theirs, frame, plane_x))
                    rows["again"].append(ed(twice, theirs, frame, plane_x))
            if got["errors"]:
                print(f"  errors: {got['errors'][:3]}")
        m = {k: float(np.mean(v)) for k, v in rows.items()}
        print(f"| {level} ({per_level} acq., {len(rows['stream'])} slices) | {m['stream']:.2f} / {m['stream_twin']:.2f} "
              f"| {m['predict']:.2f} / {m['predict_twin']:.2f} | {m['between']:.2f} "
              f"(|diff of means| {abs(m['stream'] - m['predict']):.2f}) | {m['again']:.2f} "
              f"| {np.percentile(lat['server'], 50):.1f} / {np.percentile(lat['server'], 95):.1f} ms "
              f"| {np.percentile(lat['rtt'], 95):.1f} ms |")


def whole_field(server: Server, volumes: list, rng: np.random.Generator, count: int = 3) -> None:
    """Whole-uterus stacks (the localiser's held-out generator, 256-400 mm fields of view) without masks."""
    rows = {"server": [], "rtt": [], "found": 0, "brain": 0, "both": 0, "slices": 0}
    for i in range(count):
        vol = volumes[i % len(volumes)]
        image, mask = synth_stack(HeadModel.from_arrays(vol.image, vol.mask, vol.affine), rng, "heldout")
        n = image.array.shape[2]
        got = stream(server.url, [sent_slices(image, None, interleaved(n), f"uterus{i}")])
        rows["server"] += got["server"]
        rows["rtt"] += got["rtt"]
        for k in range(n):
            found = got["last"][(f"uterus{i}", k)]["reason"] != "empty"
            brain = mask[:, :, k].sum() * np.prod(image.spacing[:2]) > 100.0
            rows["found"] += found
            rows["brain"] += brain
            rows["both"] += found and brain
            rows["slices"] += 1
    print(f"\n## Whole-uterus stacks without masks ({count} stacks, {image.array.shape[0]}-px slices; localiser per "
          f"slice), MC-100\n- server p50 / p95 {np.percentile(rows['server'], 50):.1f} / "
          f"{np.percentile(rows['server'], 95):.1f} ms; round trip p95 {np.percentile(rows['rtt'], 95):.1f} ms\n"
          f"- slices with a brain (> 1 cm2): {rows['brain']}; posed as brain: {rows['found']}, of them with a brain "
          f"{rows['both']} (of {rows['slices']} slices)")


def interleaved(n: int) -> np.ndarray:
    return np.concatenate([np.arange(0, n, 2), np.arange(1, n, 2)])


def load(server: Server, volumes: list, rng: np.random.Generator, sessions: int, pace: float) -> None:
    stacks = simulate_acquisition(volumes[1].image, volumes[1].mask, volumes[1].affine, rng, "mild")
    slices = [acquired(s) for s in stacks]
    with tempfile.TemporaryDirectory() as tmp:
        files, masks = [], []
        for s in stacks:
            files.append(Path(tmp) / f"{s.orientation}.nii.gz")
            masks.append(Path(tmp) / f"{s.orientation}_mask.nii.gz")
            write_volume(s.volume, files[-1])
            write_volume(s.mask, masks[-1])
        with SVRnetClient(server.url, timeout=600) as svr:
            svr.predict(files, masks)
            t = time.perf_counter()
            svr.predict(files, masks)
            idle = time.perf_counter() - t
            results: list[dict] = []
            threads = [threading.Thread(target=lambda: results.append(stream(server.url, slices, pace))) for _ in range(sessions)]
            for th in threads:
                th.start()
            time.sleep(3.0)
            t = time.perf_counter()
            svr.predict(files, masks)
            busy = time.perf_counter() - t
            for th in threads:
                th.join()
    server_lat = np.concatenate([r["server"] for r in results])
    errors = sum(len(r["errors"]) for r in results)
    print(f"\n## Load: {sessions} sessions at {pace} s a slice ({len(results)} finished, {errors} errors)")
    print(f"- /v1/predict, 3 x 128 x 128: idle {idle:.2f} s, beside the sessions {busy:.2f} s (x{busy / idle:.2f})")
    print(f"- poses under load: server p50 / p95 {np.percentile(server_lat, 50):.1f} / {np.percentile(server_lat, 95):.1f} ms")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--levels", default="mild,moderate,jumps")
    ap.add_argument("--per-level", type=int, default=2)
    ap.add_argument("--sessions", type=int, default=32)
    ap.add_argument("--pace", type=float, default=1.0, help="seconds between slices of a loaded session")
    ap.add_argument("--skip", default="", help="comma-separated parts to skip: accuracy, field, load")
    args = ap.parse_args()
    print(f"machine: {cpu_description()}")
    skip = set(args.skip.split(","))
    with tempfile.TemporaryDirectory() as data:
        server = Server(Path(data), Path(data) / "server.log", max_concurrent="2",
                        stream_max_sessions=str(max(32, args.sessions)))
        try:
            served = load_model(ROOT / "service" / "models" / "default" / "model.onnx").info
            plane_x = served.symmetry_plane_x_mm
            volumes, rng = load_volumes(validation_volumes(served.metadata)), np.random.default_rng(7)
            if "accuracy" not in skip:
                accuracy(args.levels.split(","), args.per_level, server, plane_x, volumes, rng)
            if "field" not in skip:
                whole_field(server, volumes, rng)
            if "load" not in skip:
                load(server, volumes, rng, args.sessions, args.pace)
        finally:
            server.kill_group()


if __name__ == "__main__":
    main()
