"""The numeric core must not pull in the web stack or the deep-learning stack."""

import subprocess
import sys


def test_geometry_imports_neither_fastapi_torch_nor_onnxruntime() -> None:
    code = ("import sys, service.geometry; "
            "print([m for m in ('fastapi', 'torch', 'onnxruntime') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
