"""The service's imports follow the data and never loop: io -> preprocess -> inference ->
consistency -> pipeline -> streaming -> api -> mrd, with the numeric core (geometry, core) below
them all and reconstruction and jobs apart."""

from __future__ import annotations

import ast
from pathlib import Path

SERVICE = Path(__file__).resolve().parents[1] / "service"
RANK = {"core": 0, "geometry": 0, "io": 1, "preprocess": 2, "inference": 3, "consistency": 4, "pipeline": 5, "streaming": 6, "api": 7, "mrd": 8}


def modules() -> dict[str, Path]:
    out = {}
    for p in SERVICE.rglob("*.py"):
        parts = p.relative_to(SERVICE.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


def imports(path: Path, known: dict[str, Path], top_level: bool) -> set[str]:
    """The service modules ``path`` imports (everywhere, or only at its top level)."""
    tree = ast.parse(path.read_text())
    out = set()
    for node in tree.body if top_level else ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("service"):
            subs = {f"{node.module}.{a.name}" for a in node.names} & set(known)
            out |= subs or ({node.module} & set(known))
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names} & set(known)
    return out


def test_no_module_imports_itself_through_others() -> None:
    known = modules()
    graph = {m: imports(p, known, top_level=False) - {m} for m, p in known.items()}
    state: dict[str, int] = {}

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for n in graph[m]:
            assert state.get(n) != 1, " -> ".join(path + [m, n])
            if n not in state:
                visit(n, path + [m])
        state[m] = 2

    for m in graph:
        if m not in state:
            visit(m, [])


def test_a_layer_imports_only_the_layers_below_it() -> None:
    known = modules()
    layer = lambda m: m.split(".")[1] if m.count(".") else ""  # noqa: E731
    wrong = [(m, n) for m, p in known.items() for n in imports(p, known, top_level=True)
             if layer(m) in RANK and layer(n) in RANK and RANK[layer(n)] > RANK[layer(m)]]
    assert not wrong, wrong
    numeric = [(m, n) for m, p in known.items() if layer(m) in ("geometry",)
               for n in imports(p, known, top_level=False) if layer(n) not in ("geometry", "")]
    assert not numeric, numeric
