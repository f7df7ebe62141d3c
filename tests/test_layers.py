"""The service's imports follow the data and never loop: io -> preprocess -> inference -> consistency
-> pipeline -> streaming -> api -> mrd, with the numeric core (geometry, core) below them all and
reconstruction and jobs apart. Nor do the training code's and the client's imports loop."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SERVICE = Path(__file__).resolve().parents[1] / "service"
RANK = {"core": 0, "geometry": 0, "io": 1, "preprocess": 2, "inference": 3, "consistency": 4, "pipeline": 5, "streaming": 6, "api": 7, "mrd": 8}


def modules(package: str = "service") -> dict[str, Path]:
    out = {}
    for p in (SERVICE.parent / package).rglob("*.py"):
        parts = p.relative_to(SERVICE.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


def imported(path: Path, top_level: bool = False) -> list[tuple[str, list[str]]]:
    """``(module, names)`` of every absolute import statement of ``path`` (everywhere, lazy ones inside
    functions too, or only at its top level): ``from m import a, b`` is ``(m, [a, b])``, ``import m``
    is ``(m, [])``."""
    tree = ast.parse(path.read_text())
    out = []
    for node in tree.body if top_level else ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and not node.level:
            out.append((node.module, [a.name for a in node.names]))
        elif isinstance(node, ast.Import):
            out.extend((a.name, []) for a in node.names)
    return out


def imports(path: Path, known: dict[str, Path], top_level: bool) -> set[str]:
    """The service modules ``path`` imports (everywhere, or only at its top level)."""
    out = set()
    for module, names in imported(path, top_level):
        subs = {f"{module}.{n}" for n in names} & set(known)
        out |= subs or ({module} & set(known))
    return out


@pytest.mark.parametrize("package", ["service", "model_export", "client"])
def test_no_module_imports_itself_through_others(package: str) -> None:
    known = modules(package)
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


def _layer(module: str) -> str:
    return module.split(".")[1] if module.count(".") else ""


def _upward(known: dict, top_level: bool) -> list[tuple[str, str]]:
    """``(module, imported)`` where a layer imports one above it (``top_level``: module-level imports
    alone; else every import, those inside functions too)."""
    return [(m, n) for m, p in known.items() for n in imports(p, known, top_level=top_level)
            if _layer(m) in RANK and _layer(n) in RANK and RANK[_layer(n)] > RANK[_layer(m)]]


def test_a_layer_imports_only_the_layers_below_it() -> None:
    known = modules()
    wrong = _upward(known, top_level=True)
    assert not wrong, wrong
    numeric = [(m, n) for m, p in known.items() if _layer(m) in ("geometry",)
               for n in imports(p, known, top_level=False) if _layer(n) not in ("geometry", "")]
    assert not numeric, numeric


ROOT = SERVICE.parent


def _all_imports(package: str) -> list[tuple[str, str]]:
    """``(module, imported)`` for every import statement of ``package``, lazy ones inside functions too."""
    return [(".".join(p.relative_to(ROOT).with_suffix("").parts), module)
            for p in (ROOT / package).rglob("*.py") for module, _ in imported(p)]


def _top(name: str) -> str:
    return name.split(".")[0]


def test_lazy_imports_inside_functions_follow_the_layers_too() -> None:
    wrong = _upward(modules(), top_level=False)
    assert not wrong, wrong


def test_reconstruction_and_jobs_stay_apart_from_the_front_ends() -> None:
    """Reconstruction is a library under the jobs: it imports neither the jobs nor the request layers
    (pipeline, streaming, api, mrd); the jobs import no front end (streaming, api, mrd) either."""
    banned = {"reconstruction": {"jobs", "pipeline", "streaming", "api", "mrd"},
              "jobs": {"streaming", "api", "mrd"}}
    wrong = {(m, n) for m, n in _all_imports("service") if n.startswith("service.") and n.count(".") >= 1
             and m.split(".")[1] in banned and n.split(".")[1] in banned[m.split(".")[1]]}
    assert not wrong, sorted(wrong)


def test_the_numeric_core_imports_no_web_or_deep_learning_stack_anywhere() -> None:
    heavy = {"fastapi", "starlette", "torch", "onnxruntime", "uvicorn", "pydantic", "client", "model_export"}
    wrong = [(m, n) for m, n in _all_imports("service") if m.startswith("service.geometry") and _top(n) in heavy]
    assert not wrong, wrong


def test_the_packages_depend_one_way() -> None:
    """``model_export`` builds on ``service``, never the reverse; the client is a package of its own
    that imports neither; the service imports of the client only its standard-library launcher
    (:mod:`client.launch`, which ``svrnet`` and the server commands share)."""
    assert not [(m, n) for m, n in _all_imports("client") if _top(n) in ("service", "model_export")]
    assert not [(m, n) for m, n in _all_imports("service") if _top(n) == "model_export"]
    assert {n for _, n in _all_imports("service") if _top(n) == "client"} <= {"client.launch"}


def test_only_the_api_and_the_app_factory_import_the_web_framework() -> None:
    wrong = [(m, n) for m, n in _all_imports("service") if _top(n) in ("fastapi", "starlette")
             and not m.startswith("service.api.") and m != "service.main"]
    assert not wrong, wrong
