"""``svrnet-train localiser ship``: a new folder (never the shipped model's by default), the checkpoint
beside the model by its sha256, and a card written from what was shipped, a quick look marked as one."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
from typer.testing import CliRunner

from model_export.localiser.cli import app
from model_export.localiser.train import train

ENV = {"COLUMNS": "250"}


def _measured(localiser, heldout: Path, pose_stacks: int, pose_scenes: int = 10) -> dict:  # noqa: ANN001
    """:func:`~model_export.localiser.evaluate.measure` on the held-out shards alone (no real scans, no
    pose network): the figures a card is written from, in seconds."""
    from model_export.localiser.evaluate import heldout_dice

    held = heldout_dice(localiser, heldout)
    dice = [r["dice"] for r in held]
    summary = {"heldout_median_dice": float(np.median(dice)), "heldout_min_dice": float(np.min(dice)),
               "heldout_stacks": len(held), "real_dice": [], "heldout_t2_like_median_dice": float(np.median(dice)),
               "heldout_random_contrast_median_dice": float("nan"), "real_without_mask": [],
               "poses_real_median_ed_mm": None, "poses_real_latency_ratio": None, "poses_heldout_median_ed_mm": None,
               "poses_heldout_repeat_median_ed_mm": None, "latency_ms_320x320x22": 12.0,
               "onnx_mb": localiser.path.stat().st_size / 2**20, "pose_scenes": pose_scenes,
               "poses_truth_median_ed_mm": {}}
    return {"summary": summary, "heldout": held, "real": [], "poses_real": None, "poses_heldout": [],
            "poses_truth": {}}


@pytest.fixture()
def quick_checkpoint(shards: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    from model_export.localiser import evaluate

    monkeypatch.setattr(evaluate, "measure", _measured)
    return train(shards, tmp_path / "quick.pt", steps=3, seed=9, width=4, depth=2, batch=4, crop=32, threads=1)


def test_the_card_says_what_was_shipped_and_that_it_is_a_quick_look(quick_checkpoint: Path, shards: Path,
                                                                    tmp_path: Path) -> None:
    out = tmp_path / "next"
    result = CliRunner().invoke(app, ["ship", str(quick_checkpoint), "--heldout", str(shards), "--out", str(out),
                                      "--version", "0.0.1-quick", "--pose-scenes", "0"], env=ENV)
    assert result.exit_code == 0, result.output
    sha = hashlib.sha256(quick_checkpoint.read_bytes()).hexdigest()
    assert hashlib.sha256((out / "checkpoint.pt").read_bytes()).hexdigest() == sha
    meta = ort.InferenceSession(str(out / "model.onnx"), providers=["CPUExecutionProvider"]).get_modelmeta()
    assert meta.custom_metadata_map["checkpoint_sha256"] == sha
    shipped = json.loads((out / "evaluation.json").read_text())["shipped"]
    assert shipped["checkpoint"]["sha256"] == sha and shipped["training"]["seed"] == 9
    card = (out / "card.md").read_text()
    assert card.startswith("# Brain localiser `0.0.1-quick`")
    assert "Quick look, not a model to use" in card and "3 training steps" in card and "2 training shards" in card
    assert "0 pose scenes" in card and "budget: 3 steps, reproducible" in card
    assert "| seed | 9 |" in card and f"`{shards.name}`" in card and sha in card
    assert shipped["training"]["data"]["manifest_sha256"] in card
    assert "--steps 3 --seed 9 --width 4 --depth 2" in card                   # the command that repeats the run
    assert "1.2.0" not in card and "L4.pt" not in card and "fine-tuned" not in card   # nothing of another version


def test_ship_needs_an_out_folder_and_refuses_one_with_files(quick_checkpoint: Path, shards: Path, tmp_path: Path,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)                     # where the shipped model's folder would be, relative
    args = ["ship", str(quick_checkpoint), "--heldout", str(shards), "--version", "0.0.2", "--pose-scenes", "0"]
    result = CliRunner().invoke(app, args, env=ENV)
    assert result.exit_code == 2 and "--out" in result.output
    assert not (tmp_path / "service").exists()
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "card.md").write_text("a model of its own\n")
    result = CliRunner().invoke(app, [*args, "--out", str(taken)], env=ENV)
    assert result.exit_code == 2 and "--force" in result.output
    assert [p.name for p in taken.iterdir()] == ["card.md"] and (taken / "card.md").read_text() == "a model of its own\n"
    result = CliRunner().invoke(app, [*args, "--out", str(taken), "--force"], env=ENV)
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in taken.iterdir()) == ["card.md", "checkpoint.pt", "evaluation.json", "model.onnx"]
    assert "`0.0.2`" in (taken / "card.md").read_text()
    inside = ["ship", str(taken / "checkpoint.pt"), "--heldout", str(shards), "--version", "0.0.3", "--pose-scenes",
              "0", "--out", str(taken), "--force"]                 # the folder ship replaces holds its checkpoint
    result = CliRunner().invoke(app, inside, env=ENV)
    assert result.exit_code == 2 and "ship replaces" in result.output and (taken / "checkpoint.pt").exists()


def test_a_ship_that_fails_leaves_no_folder_and_says_why_in_one_line(quick_checkpoint: Path, shards: Path,
                                                                   tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Inputs that cannot make a localiser are refused before anything is exported, and a step that
    fails later leaves nothing: a server never finds a half-written localiser folder."""
    from model_export.localiser import evaluate

    out = tmp_path / "next"
    args = ["ship", str(quick_checkpoint), "--out", str(out), "--version", "0.0.3", "--pose-scenes", "0"]
    no_stacks = tmp_path / "no_stacks"
    no_stacks.mkdir()
    with np.load(next(shards.glob("*.npz"))) as z:
        np.savez(no_stacks / "a.npz", **{k: z[k] for k in z.files if k != "stack"})
    for heldout, said in ((tmp_path / "nowhere", "holds no shards"), (no_stacks, "keep no stack")):
        result = CliRunner().invoke(app, [*args, "--heldout", str(heldout)], env=ENV)
        assert result.exit_code == 2 and said in result.output and "Traceback" not in result.output, result.output
    pose = tmp_path / "pose.pt"
    import torch

    torch.save({"config": {"backbone": "resnet"}}, pose)
    result = CliRunner().invoke(app, ["ship", str(pose), *args[2:], "--heldout", str(shards)], env=ENV)
    assert result.exit_code == 2 and "not a localiser checkpoint" in result.output, result.output

    def broken(*a, **k):  # noqa: ANN002, ANN003, ANN202
        raise RuntimeError("a measurement failed")

    monkeypatch.setattr(evaluate, "measure", broken)
    result = CliRunner().invoke(app, [*args, "--heldout", str(shards)], env=ENV)
    assert result.exit_code != 0 and isinstance(result.exception, RuntimeError)
    assert not [p.name for p in tmp_path.iterdir() if "next" in p.name]          # neither the folder nor its draft
