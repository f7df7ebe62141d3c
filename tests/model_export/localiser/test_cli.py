"""The localiser's command line: what it refuses before it generates anything."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from model_export.localiser.cli import app


def test_data_refuses_a_motion_the_scenes_do_not_know(tmp_path: Path) -> None:
    """``--motion extreme`` (any orientation per slice, which a head in a scene cannot take) is a usage
    error naming the option and the levels it takes, and no shard folder is made."""
    out = tmp_path / "shards"
    result = CliRunner().invoke(app, ["data", "--out", str(out), "--count", "1", "--motion", "extreme"],
                                env={"COLUMNS": "250"})
    assert result.exit_code == 2
    assert "--motion" in result.output and "independent" in result.output
    assert not out.exists()


def test_train_and_average_refuse_what_is_no_localiser_checkpoint_in_one_line(tmp_path: Path) -> None:
    """A data folder that is not there, a pose network's checkpoint where a localiser's belongs (as
    ``--out`` to resume, ``--init``, either of ``average``'s), a file that is not there: each a usage
    error naming the option, not a traceback from inside the training."""
    import torch

    pose = tmp_path / "pose.pt"
    torch.save({"config": {"backbone": "resnet", "width": 1.0}, "model": {}}, pose)
    (tmp_path / "shards").mkdir()
    train = ["train", "--steps", "1", "--data", str(tmp_path / "shards")]
    for args, hint, said in (
            (["train", "--steps", "1", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "a.pt")], "--data",
             "not a folder of shards"),
            ([*train, "--out", str(pose)], "--out", "not a localiser checkpoint"),
            ([*train, "--out", str(tmp_path / "a.pt"), "--init", str(tmp_path / "nope.pt")], "--init", "no such file"),
            (["average", str(pose), str(pose), "--out", str(tmp_path / "m.pt")], "BASE", "not a localiser checkpoint"),
            (["average", str(tmp_path / "nope.pt"), str(pose), "--out", str(tmp_path / "m.pt")], "BASE", "no such file")):
        result = CliRunner().invoke(app, args, env={"COLUMNS": "250"})
        assert result.exit_code == 2, (args, result.output)
        assert hint in result.output and said in result.output and "Traceback" not in result.output, result.output
    assert not (tmp_path / "a.pt").exists() and not (tmp_path / "m.pt").exists()


def test_train_says_what_it_did_and_logs_its_last_step(shards: Path, tmp_path: Path) -> None:
    """A short run logs its last step (the log is written at checkpoints, minutes apart); run again
    with the steps it has done, it says there is nothing to do and leaves the checkpoint as it is."""
    import json

    out = tmp_path / "l.pt"
    args = ["train", "--data", str(shards), "--out", str(out), "--steps", "2", "--width", "4", "--depth", "2",
            "--batch", "2", "--threads", "1"]
    first = CliRunner().invoke(app, args, env={"COLUMNS": "250"})
    assert first.exit_code == 0 and f"{out}: steps 0 to 2" in first.output, first.output
    logged = [json.loads(line) for line in Path(f"{out}.log").read_text().splitlines()]
    assert logged[-1]["step"] == 2 and logged[-1]["loss"] > 0
    written = out.read_bytes()
    again = CliRunner().invoke(app, args, env={"COLUMNS": "250"})
    assert again.exit_code == 0 and "nothing to do" in again.output and "2 steps" in again.output, again.output
    assert out.read_bytes() == written and len(Path(f"{out}.log").read_text().splitlines()) == len(logged)
