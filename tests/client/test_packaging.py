"""The ``client`` extra alone must carry every third-party module the client imports (and no heavy one)."""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def client_imports() -> set[str]:
    names: set[str] = set()
    for path in (ROOT / "client").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names and n not in ("client", "__future__")}


def test_client_extra_covers_every_import_and_nothing_heavy() -> None:
    extra = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["optional-dependencies"]["client"]
    required = {re.split(r"[<>=!~\[ ;]", r, maxsplit=1)[0].lower() for r in extra}
    base = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"].get("dependencies", [])
    required |= {re.split(r"[<>=!~\[ ;]", r, maxsplit=1)[0].lower() for r in base}
    imported = {n.lower() for n in client_imports()}
    assert imported <= required, f"imported by client/ but not in the client extra: {sorted(imported - required)}"
    assert not required & {"torch", "onnxruntime", "simpleitk", "onnx"}
