"""Render the OpenAPI page (/docs) as a user sees it: a real server and headless Chromium.

    .venv/bin/python tools/docs_screenshot.py [out.png]

Needs Debian's ``chromium`` (``apt-get install chromium``). Exits non-zero when the page does not
render (no Swagger UI title in the DOM).
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--virtual-time-budget=8000", "--window-size=1280,1600"]


def main(out: Path) -> int:
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        print("chromium not installed (apt-get install chromium)", file=sys.stderr)
        return 2
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = dict(os.environ, SVRNET_PORT=str(port), SVRNET_LOG_LEVEL="warning",
               SVRNET_DATA_DIR=tempfile.mkdtemp(prefix="svrnet-docs-"))
    server = subprocess.Popen([sys.executable, "-c", "from service.main import run; run()"], cwd=ROOT, env=env)
    try:
        url = f"http://127.0.0.1:{port}"
        for _ in range(100):
            try:
                urllib.request.urlopen(f"{url}/healthz", timeout=1)
                break
            except OSError:
                time.sleep(0.2)
        profile = tempfile.mkdtemp(prefix="chromium-")
        subprocess.run([chromium, *FLAGS, f"--user-data-dir={profile}", f"--screenshot={out}", f"{url}/docs"],
                       check=True, capture_output=True, timeout=120)
        dom = subprocess.run([chromium, *FLAGS, f"--user-data-dir={profile}", "--dump-dom", f"{url}/docs"],
                             check=True, capture_output=True, text=True, timeout=120).stdout
        ok = "swagger-ui" in dom and "/v1/predict" in dom
        print(f"screenshot: {out} ({out.stat().st_size} bytes); Swagger UI rendered with /v1/predict: {ok}")
        return 0 if ok else 1
    finally:
        server.terminate()
        server.wait(10)


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1] if len(sys.argv) > 1 else "docs.png").resolve()))
