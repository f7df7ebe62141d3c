"""A localiser training run of a step budget is reproducible, and its checkpoint says what made it."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from model_export.localiser.train import main, train

TINY = {"width": 4, "depth": 2, "batch": 4, "crop": 32, "threads": 1}


def _weights(path: Path) -> dict[str, torch.Tensor]:
    return torch.load(path, weights_only=False)["model"]


def test_the_same_seed_steps_and_shards_give_the_same_weights(shards: Path, tmp_path: Path) -> None:
    """Two 3-step runs of one seed on one folder end with identical weights; another seed does not."""
    a, b = (train(shards, tmp_path / f"{name}.pt", steps=3, seed=5, **TINY) for name in "ab")
    c = train(shards, tmp_path / "c.pt", steps=3, seed=6, **TINY)
    wa, wb, wc = _weights(a), _weights(b), _weights(c)
    assert wa.keys() == wb.keys()
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    assert not all(torch.equal(wa[k], wc[k]) for k in wa)
    assert torch.load(a, weights_only=False)["step"] == 3


def test_a_checkpoint_records_its_seed_steps_data_and_commit(shards: Path, tmp_path: Path) -> None:
    """The record names the shard folder (not where it lies), its shards and their generator settings,
    and hashes the list: a folder with one shard more is another data set."""
    ckpt = train(shards, tmp_path / "loc.pt", steps=2, seed=7, lr=1e-3, **TINY)
    record = torch.load(ckpt, weights_only=False)["training"]
    assert (record["seed"], record["steps"], record["minutes"], record["to_step"], record["lr"]) == (7, 2, None, 2, 1e-3)
    data = record["data"]
    assert data["folder"] == shards.name and data["shards"] == 2
    assert data["names"] == ["train-000000.npz", "train-000001.npz"] and len(data["manifest_sha256"]) == 64
    [generator] = data["generators"]
    assert generator["seeds"] == "0-1" and generator["settings"]["style"] == "train"
    assert generator["settings"]["volumes"] == ["STA30"] and generator["settings"]["grid_mm"] == 4.0
    assert str(shards.parent) not in json.dumps(record)                        # no absolute path of the data
    commit = record["commit"]
    assert commit == "unknown" or len(commit.removesuffix("-dirty")) == 40
    assert [(r["from_step"], r["to_step"]) for r in record["runs"]] == [(0, 2)]

    more = tmp_path / "more"
    shutil.copytree(shards, more)
    shutil.copy(shards / "train-000001.npz", more / "train-000002.npz")
    other = torch.load(train(more, tmp_path / "more.pt", steps=1, **TINY), weights_only=False)["training"]["data"]
    assert other["shards"] == 3 and other["manifest_sha256"] != data["manifest_sha256"]

    resumed = torch.load(train(shards, ckpt, steps=4, seed=7, **TINY), weights_only=False)
    assert resumed["step"] == 4
    assert [(r["from_step"], r["to_step"]) for r in resumed["training"]["runs"]] == [(0, 2), (2, 4)]


def test_a_step_budget_anneals_over_its_steps_and_one_budget_is_required(shards: Path, tmp_path: Path) -> None:
    from model_export.localiser.train import lr_at

    assert lr_at(1.0, 0, 10) == 1.0 and lr_at(1.0, 5, 10) == pytest.approx(0.5) and lr_at(1.0, 10, 10) == 0.0
    with pytest.raises(ValueError, match="one budget"):
        train(shards, tmp_path / "x.pt", **TINY)
    with pytest.raises(ValueError, match="one budget"):
        train(shards, tmp_path / "x.pt", 1.0, steps=3, **TINY)
    with pytest.raises(SystemExit):                              # the module's command line asks for one too
        main(["--data", str(shards), "--out", str(tmp_path / "x.pt")])
    ckpt = main(["--data", str(shards), "--out", str(tmp_path / "m.pt"), "--steps", "2", "--seed", "3", "--width", "4",
                 "--depth", "2", "--batch", "4", "--crop", "32", "--threads", "1"])
    state = torch.load(ckpt, weights_only=False)
    assert state["step"] == 2 and state["training"]["seed"] == 3
    assert np.isfinite([float(v.float().abs().sum()) for v in state["model"].values()]).all()
