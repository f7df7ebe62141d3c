"""``svrnet-train`` without the training packages says what to install, in one line."""

from __future__ import annotations

from tests.client.test_launch import run_without


def test_svrnet_train_without_typer_names_the_extra_to_install() -> None:
    r = run_without("typer", "model_export.launch")
    assert r.returncode == 1 and "typer is missing" in r.stderr and '".[train]"' in r.stderr
    assert "Traceback" not in r.stderr
