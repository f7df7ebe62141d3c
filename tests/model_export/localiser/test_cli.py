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
