"""``svrnet-train`` without the training packages says what to install, in one line."""

from __future__ import annotations

from tests.client.test_launch import run_without


def test_svrnet_train_without_typer_names_the_extra_to_install() -> None:
    r = run_without("typer", "model_export.launch")
    assert r.returncode == 1 and "typer is missing" in r.stderr and '"svrnet[train]"' in r.stderr and "whl/cpu" in r.stderr
    assert "Traceback" not in r.stderr


def test_svrnet_train_in_a_client_only_install_names_the_extra_too() -> None:
    """A client-only install has typer but not the server's packages the training imports (scipy)."""
    r = run_without("scipy", "model_export.launch")
    assert r.returncode == 1 and "scipy is missing" in r.stderr and '"svrnet[train]"' in r.stderr
    assert "Traceback" not in r.stderr
