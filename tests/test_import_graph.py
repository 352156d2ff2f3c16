"""The package's import graph: no circles, and every import runs down the layers.

Module-level, function-level and TYPE_CHECKING imports all count.

- **No circle** anywhere in ``msdnet``: no module imports, directly or through others, a module
  that imports it back.
- **Roots** (``ROOT_MAY_IMPORT``): ``runtime`` <- ``training`` <- ``export``; ``benchmarks`` imports
  the runtime, and training / export only in the modules of ``TORCH_SIDE``, where a comparison
  needs the torch models or the exporter; ``models`` (the shipped models, data) imports nothing
  and any root may import it to find them.
- **runtime/** keeps its sub-packages in order: the core (``errors`` <- ``spec``: the grid, schedules
  and range thresholds <- ``model``: the artifact <- ``providers``: engine choice and sessions <-
  ``engine``: the Pipeline) <- ``io`` <- ``metrics`` / ``sim`` <- ``frontends``; nothing imports a
  front-end but another front-end.
- **training/** likewise: the configs (``published_config`` <- ``config``) <- ``data`` <- ``nn``
  <- ``models`` <- ``recipe`` <- ``cli`` <- ``main`` (the ``msdnet-train`` group).
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ROOTS = ("runtime", "training", "export", "benchmarks", "models")
# root -> the other roots its modules may import
ROOT_MAY_IMPORT = {
    "runtime": {"models"},
    "training": {"runtime", "models"},
    "export": {"runtime", "training", "models"},
    "benchmarks": {"runtime", "models"},
    "models": set(),
}
# benchmark modules that compare against the torch side, so may import training and export
TORCH_SIDE = {
    "msdnet.benchmarks.params": "parameter counts of the torch models against the papers' tables",
    "msdnet.benchmarks.conditioning": "runs a trained R2LDM checkpoint's torch U-Net",
    "msdnet.benchmarks.stages": "runs each stage of a trained checkpoint in torch",
    "msdnet.benchmarks.eval_methods": "scores torch checkpoints beside exported models",
    "msdnet.benchmarks.latency.models": "exports random torch twins of the timed models",
    "msdnet.benchmarks.latency.old_graphs": "exports the same random model in the old graph form",
    "msdnet.benchmarks.latency.peers": "times the torch modules of each graph as a peer engine",
    "msdnet.benchmarks.latency.timing": "times torch eager beside the engines",
    "msdnet.benchmarks.latency.steps": "reads a checkpoint's config for the step sweep",
    "msdnet.benchmarks.latency.head": "times the coarse-to-fine head at the gate export calibrates",
    "msdnet.benchmarks.latency.encoder_forms": "exports a torch encoder in the pair and rulebook forms",
    "msdnet.benchmarks.training_speed_worker": "trains the torch models to time their steps",
}
# runtime sub-package -> the sub-packages its modules may import (besides its own)
_CORE = ("errors", "spec", "model", "providers", "engine")  # each imports only those before it
MAY_IMPORT = {
    "offline": set(),  # the engines' telemetry off (runtime/__init__.py applies it first)
    **{part: set(_CORE[:i]) for i, part in enumerate(_CORE)},
    "io": {"errors", "spec", "engine", "model"},
    "metrics": {"errors", "spec", "engine", "io"},
    "sim": {"errors", "spec", "engine", "model", "io"},
    "frontends": {"errors", "spec", "engine", "model", "providers", "io", "metrics", "sim"},
}
# training sub-package (or top-level module) -> the parts of training its modules may import
_TRAINING_ORDER = ("published_config", "config", "data", "nn", "models", "recipe", "cli", "main")
TRAINING_MAY_IMPORT = {part: set(_TRAINING_ORDER[:i]) for i, part in enumerate(_TRAINING_ORDER)}


def _modules(roots: tuple[str, ...] = ROOTS) -> dict[str, Path]:
    mods = {}
    for root in roots:
        for f in (REPO / root).rglob("*.py"):
            parts = list(f.relative_to(REPO / root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(["msdnet", root, *parts])] = f
    return mods


def _graph(mods: dict[str, Path]) -> dict[str, set[str]]:
    """module -> the msdnet modules it imports (``from pkg import mod`` counts as pkg.mod)."""
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for name, file in mods.items():
        for node in ast.walk(ast.parse(file.read_text(encoding="utf-8"))):
            targets: list[str] = []
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("msdnet."):
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


def test_package_has_no_import_circles():
    assert _cycles(_graph(_modules())) == []


def test_the_check_sees_a_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c"]]


def _root(module: str) -> str:
    return module.split(".")[1]


def test_roots_import_only_those_below():
    wrong = sorted(
        f"{a} -> {b}"
        for a, targets in _graph(_modules()).items()
        for b in targets
        if _root(b) != _root(a)
        and _root(b) not in ROOT_MAY_IMPORT[_root(a)]
        and not (a in TORCH_SIDE and _root(b) in {"training", "export"})
    )
    assert wrong == []


def test_torch_side_list_names_real_modules():
    assert set(TORCH_SIDE) <= set(_modules(("benchmarks",)))


def _part(module: str) -> str:
    """``msdnet.runtime.io.datasets.vod`` -> ``io``; ``msdnet.training.cli`` -> ``cli``; the
    package itself -> ``""``."""
    return (module.split(".") + [""])[2]


def _wrong_order(root: str, may_import: dict[str, set[str]]) -> list[str]:
    graph = _graph(_modules((root,)))
    return sorted(
        f"{a} -> {b}"
        for a, targets in graph.items()
        for b in targets
        if _part(a) in may_import and _part(b) != _part(a) and _part(b) not in may_import[_part(a)]
    )


def test_runtime_is_in_its_sub_packages():
    loose = [m for m in _modules(("runtime",)) if _part(m) not in MAY_IMPORT and m != "msdnet.runtime"]
    assert loose == [], f"runtime modules outside the sub-packages {sorted(MAY_IMPORT)}: {loose}"


def test_runtime_sub_packages_import_only_those_below():
    assert _wrong_order("runtime", MAY_IMPORT) == []


def test_training_is_in_its_sub_packages():
    loose = [
        m for m in _modules(("training",)) if _part(m) not in TRAINING_MAY_IMPORT and m != "msdnet.training"
    ]
    assert loose == [], f"training modules outside {sorted(TRAINING_MAY_IMPORT)}: {loose}"


def test_training_parts_import_only_those_below():
    assert _wrong_order("training", TRAINING_MAY_IMPORT) == []
