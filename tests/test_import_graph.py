"""runtime/ has no import circles: no module imports, directly or through others, a module that
imports it back (module-level, function-level and TYPE_CHECKING imports all count). And its
sub-packages keep their order: ``errors`` <- the core (``engine``, ``model``: the Pipeline reads
the artifact, the artifact reads the engine's grid and schedule) <- ``io`` <- ``sim`` <-
``frontends``; nothing imports a front-end but another front-end."""

from __future__ import annotations

import ast
from pathlib import Path

RUNTIME = Path(__file__).resolve().parents[1] / "runtime"
# sub-package -> the sub-packages its modules may import (besides its own)
MAY_IMPORT = {
    "errors": set(),
    "engine": {"errors", "model"},
    "model": {"errors", "engine"},
    "io": {"errors", "engine", "model"},
    "sim": {"errors", "engine", "model", "io"},
    "frontends": {"errors", "engine", "model", "io", "sim"},
}


def _modules() -> dict[str, Path]:
    mods = {}
    for f in RUNTIME.rglob("*.py"):
        parts = list(f.relative_to(RUNTIME).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mods[".".join(["msdnet.runtime", *parts])] = f
    return mods


def _graph(mods: dict[str, Path]) -> dict[str, set[str]]:
    """module -> the runtime modules it imports (``from pkg import mod`` counts as pkg.mod)."""
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for name, file in mods.items():
        for node in ast.walk(ast.parse(file.read_text(encoding="utf-8"))):
            targets: list[str] = []
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("msdnet.runtime"):
                subs = [f"{node.module}.{a.name}" for a in node.names]
                targets = [s for s in subs if s in mods] or [node.module]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            graph[name].update(t for t in targets if t in mods and t != name)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_runtime_has_no_import_circles():
    assert _cycles(_graph(_modules())) == []


def test_the_check_sees_a_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c"]]


def _part(module: str) -> str:
    """``msdnet.runtime.io.datasets.vod`` -> ``io``; the package itself -> ``""``."""
    return (module.split(".") + [""])[2]


def test_runtime_is_in_its_sub_packages():
    loose = [m for m in _modules() if _part(m) not in MAY_IMPORT and m != "msdnet.runtime"]
    assert loose == [], f"runtime modules outside the sub-packages {sorted(MAY_IMPORT)}: {loose}"


def test_sub_packages_import_only_those_below():
    graph = _graph(_modules())
    wrong = sorted(
        f"{a} -> {b}"
        for a, targets in graph.items()
        for b in targets
        if _part(a) in MAY_IMPORT and _part(b) != _part(a) and _part(b) not in MAY_IMPORT[_part(a)]
    )
    assert wrong == []
