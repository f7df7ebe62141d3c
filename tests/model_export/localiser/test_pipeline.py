"""Shards -> training -> ONNX: the shards hold what the service's input function gives, training
resumes from its checkpoint, and the exported graph computes what the network does."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

from model_export.localiser.export import export_onnx, load_checkpoint
from model_export.localiser.batches import draw_batch, load_shards
from model_export.localiser.train import train
from service.preprocess.localise import Localiser
from tests.model_export.localiser.conftest import GRID_MM


def test_a_shard_is_the_service_input_and_its_target(shards: Path) -> None:
    from service.io.volume import Volume
    from service.preprocess.localiser_inputs import localiser_inputs, target_maps

    with np.load(shards / "train-000000.npz") as z:
        volume = Volume(z["stack"].astype(np.float32), z["affine"])
        x, grid = localiser_inputs(volume, GRID_MM)
        assert z["slices"].shape == x[:, 1].shape
        assert np.allclose(z["slices"], x[:, 1], atol=2e-2)                  # float16 storage
        target = target_maps(z["mask"], volume, grid)
        assert np.abs(z["target"] / 255.0 - target).max() <= 1 / 255 + 1e-6
        assert z["target"].max() == 255 and z["target"].mean() < 0.1 * 255


def test_batches_are_mostly_brain_and_shaped_for_the_net(shards: Path) -> None:
    known = load_shards(shards, {})
    x, y = draw_batch(list(known.values()), np.random.default_rng(0), 8, 32)
    assert x.shape == (8, 3, 32, 32) and y.shape == (8, 1, 32, 32)
    assert (y.reshape(8, -1).max(1) > 0.5).sum() >= 4                     # 75 % drawn from brain slices


def test_training_resumes_and_the_export_computes_what_the_network_does(shards: Path, tmp_path: Path) -> None:
    ckpt = tmp_path / "loc.pt"
    train(shards, ckpt, 0.05, width=4, depth=2, batch=4, crop=32, checkpoint_s=1.0, threads=1)
    first = torch.load(ckpt, weights_only=False)["step"]
    train(shards, ckpt, 0.02, width=4, depth=2, batch=4, crop=32, threads=1)
    assert torch.load(ckpt, weights_only=False)["step"] > first > 0
    with pytest.warns(UserWarning, match="resumes its own network"):       # the options' default width
        train(shards, ckpt, steps=torch.load(ckpt, weights_only=False)["step"] + 1, batch=4, crop=32, threads=1)
    assert torch.load(ckpt, weights_only=False)["config"]["width"] == 4
    onnx_path = export_onnx(ckpt, tmp_path / "model.onnx", grid_mm=GRID_MM, version="0.0.1")
    x = np.random.default_rng(1).random((3, 3, 48, 32), np.float32)
    sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    with torch.no_grad():
        expected = load_checkpoint(ckpt)(torch.from_numpy(x)).numpy()
    assert np.allclose(sess.run(None, {"stacks": x})[0], expected, atol=1e-4)
    loc = Localiser.load(onnx_path)
    assert loc.grid_mm == GRID_MM and loc.version == "0.0.1" and len(loc.sha256) == 64


def test_contrast_augmentation_keeps_the_input_range_and_changes_neighbours_apart() -> None:
    from model_export.localiser.batches import vary_contrast

    rng = np.random.default_rng(0)
    x = np.random.default_rng(1).random((3, 32, 32)).astype(np.float32) * 1.5
    outs = [vary_contrast(x.copy(), rng) for _ in range(200)]
    assert all(o.shape == x.shape and o.dtype == np.float32 and 0 <= o.min() and o.max() <= 2 for o in outs)
    ratios = np.array([[o[c].mean() / x[c].mean() for c in range(3)] for o in outs])
    assert ratios.min() < 0.5 and ratios.max() > 1.2                       # brighter and darker
    apart = np.abs(np.log(ratios[:, 0] / ratios[:, 1])) > 0.1             # a neighbour unlike its slice
    assert 0.1 < apart.mean() < 0.7


def test_averaged_weights_lie_between_the_two_networks(tmp_path: Path) -> None:
    from model_export.localiser.net import LocaliserNet
    from model_export.localiser.train import average_weights

    paths = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        net = LocaliserNet(width=4, depth=2)
        paths.append(tmp_path / f"n{seed}.pt")
        torch.save({"model": net.state_dict(), "config": net.config, "step": seed}, paths[-1])
    out = average_weights(paths[0], paths[1], tmp_path / "avg.pt", weight=0.25)
    a, b, m = (torch.load(p, weights_only=False) for p in (*paths, out))
    key = "head.weight"
    assert torch.allclose(m["model"][key], 0.25 * b["model"][key] + 0.75 * a["model"][key])
    assert m["step"] == 1 and m["averaged"]["weight"] == 0.25
    torch.manual_seed(2)
    other = LocaliserNet(width=8, depth=2)
    torch.save({"model": other.state_dict(), "config": other.config}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="differ"):
        average_weights(paths[0], tmp_path / "other.pt", tmp_path / "bad.pt")


def test_a_checkpoint_carries_its_shards_grid_into_the_model_file(shards: Path, tmp_path: Path) -> None:
    """The shards record the grid they were made on, training writes it into the checkpoint, and the
    export takes it from there: a model file cannot claim a grid its network never learnt."""
    import shutil

    from model_export.localiser.batches import shards_grid_mm

    assert shards_grid_mm(load_shards(shards, {})) == GRID_MM
    ckpt = tmp_path / "loc.pt"
    train(shards, ckpt, 0.01, width=4, depth=2, batch=4, crop=32, threads=1)
    assert torch.load(ckpt, weights_only=False)["grid_mm"] == GRID_MM
    assert Localiser.load(export_onnx(ckpt, tmp_path / "a.onnx", version="0.0.1")).grid_mm == GRID_MM
    with pytest.raises(ValueError, match=r"grid_mm: .* 4.0 mm grid, not 2.5 mm"):
        export_onnx(ckpt, tmp_path / "b.onnx", grid_mm=2.5, version="0.0.1")
    mixed = tmp_path / "mixed"
    shutil.copytree(shards, mixed)
    with np.load(mixed / "train-000001.npz") as z:
        np.savez_compressed(mixed / "train-000001.npz", **{**dict(z), "grid_mm": np.float64(2.5)})
    with pytest.raises(ValueError, match="grids of"):
        train(mixed, tmp_path / "mixed.pt", 0.01, width=4, depth=2, batch=4, crop=32, threads=1)


def test_a_shard_still_being_written_is_not_read(shards: Path, tmp_path: Path) -> None:
    """A trainer reads its folder while a generator writes into it: half a shard is skipped, not a crash."""
    import shutil

    folder = tmp_path / "growing"
    shutil.copytree(shards, folder)
    whole = (folder / "train-000001.npz").read_bytes()
    (folder / "train-000009.npz").write_bytes(whole[: len(whole) // 2])
    assert sorted(load_shards(folder, {})) == ["train-000000.npz", "train-000001.npz"]


def test_the_generator_writes_whole_shards_of_the_training_volumes_alone(phantom_atlas: Path, tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """``python -m model_export.localiser.dataset``: shards of the training volumes (the validation
    volumes of the same folder never), each written whole under its final name."""
    from model_export.atlas import VALIDATION_VOLUMES
    from model_export.localiser import dataset

    seen: list[list[str]] = []
    real_generate = dataset.generate

    def spy(out, names, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        seen.append(list(names))
        return real_generate(out, names, *args, **kwargs)

    monkeypatch.setattr(dataset, "generate", spy)
    names = dataset.main(["--out", str(tmp_path), "--root", str(phantom_atlas), "--count", "1", "--seed", "5",
                          "--workers", "1", "--grid-mm", str(GRID_MM)])
    assert names == ["train-000005.npz"] and sorted(p.name for p in tmp_path.iterdir()) == names
    assert sorted(seen[0]) == ["SB_GA27_operated", "STA30"] and not set(seen[0]) & set(VALIDATION_VOLUMES)
    with np.load(tmp_path / names[0]) as z:
        assert float(z["grid_mm"]) == GRID_MM and z["target"].max() == 255


def test_batches_drawn_by_worker_processes_train_the_network(shards: Path, tmp_path: Path) -> None:
    """``python -m model_export.localiser.train ... --loaders 1``: the batches come from a worker
    process (a GPU host's way), and the run trains, checkpoints and records the shards' grid."""
    from model_export.localiser.batches import BatchStream
    from model_export.localiser.train import main

    x, y = next(iter(BatchStream(shards, 4, 32, seed=0)))
    assert x.shape == (4, 3, 32, 32) and y.shape == (4, 1, 32, 32) and 0 <= y.min() and y.max() <= 1
    ckpt = main(["--data", str(shards), "--out", str(tmp_path / "w.pt"), "--minutes", "0.1", "--width", "4",
                 "--depth", "2", "--batch", "4", "--crop", "32", "--threads", "1", "--loaders", "1", "--device", "cpu"])
    state = torch.load(ckpt, weights_only=False)
    assert state["step"] > 0 and state["grid_mm"] == GRID_MM and state["shards"] == 2
    assert all(v.device.type == "cpu" for v in state["model"].values())
    # Two worker processes draw different batches (each its own seed), not the same stream twice.
    loader = iter(torch.utils.data.DataLoader(BatchStream(shards, 4, 32, seed=3), batch_size=None, num_workers=2))
    first, second = next(loader), next(loader)
    assert not np.array_equal(first[0], second[0])
    with pytest.raises(FileNotFoundError, match="not a folder of shards"):      # a mistyped --data: said, not awaited
        main(["--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "x.pt"), "--minutes", "0.01"])
