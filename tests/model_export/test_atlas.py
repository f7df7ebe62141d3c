"""Where the training commands look for the atlases by default."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path


def test_the_default_atlas_folder_is_beside_a_checkout_or_where_svrnet_shared_data_says(tmp_path: Path) -> None:
    """Installed from a wheel, ``model_export`` lies in a venv with no ``../shared`` beside it: the variable
    names the data folder instead, for the atlases and the real scans alike, and a folder without the
    atlases says both ways to name one."""
    code = ("from model_export.atlas import DEFAULT_ATLAS_ROOT, list_volumes; from model_export.localiser.evaluate import "
            "REAL_SCANS; print(DEFAULT_ATLAS_ROOT); print(REAL_SCANS)\ntry:\n list_volumes(DEFAULT_ATLAS_ROOT)\n"
            "except FileNotFoundError as e:\n print(e)")
    env = {k: v for k, v in os.environ.items() if k != "SVRNET_SHARED_DATA"}
    here = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True).stdout
    assert here.splitlines()[0] == str(Path("model_export").resolve().parents[1] / "shared" / "data" / "fetal_atlas")
    there = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                           env={**env, "SVRNET_SHARED_DATA": str(tmp_path)}).stdout.splitlines()
    assert there[:2] == [str(tmp_path / "fetal_atlas"), str(tmp_path / "real_scans")]
    assert "give --root, or set SVRNET_SHARED_DATA" in there[2]
