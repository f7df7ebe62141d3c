"""The OpenAPI page renders in headless Chromium as a user sees it (skips without Chromium)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.skipif(shutil.which("chromium") is None, reason="Debian's chromium is not installed")
def test_docs_page_renders_offline(tmp_path: Path) -> None:
    out = tmp_path / "docs.png"
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "docs_screenshot.py"), str(out)], cwd=ROOT,
                       capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stdout + r.stderr
    assert out.stat().st_size > 20_000


def test_docs_assets_are_served_locally() -> None:
    from service.inference.registry import ModelRegistry
    from tests.api.conftest import make_client

    with make_client(ModelRegistry({})) as client:
        html = client.get("/docs").text
        assert "cdn" not in html.lower()
        js = [part.split('"')[0] for part in html.split('src="')[1:]]
        assert js and all(client.get(src).status_code == 200 for src in js)
