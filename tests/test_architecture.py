"""The import graph of the package: layered, no cycles between packages or modules.

Layers (lowest first; a package imports only from lower layers or, without a
cycle, its own layer): gcode, geometry -> render, analysis, simulate ->
pipeline -> monitor, evaluate, storage -> cli, web. ``errors``,
``settings_base``, ``percentile`` and ``examples`` (data files) sit below everything.
Function-local imports count too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import layerwatch

ROOT = Path(layerwatch.__file__).parent
LAYERS = [("errors", "settings_base", "percentile", "examples", "__init__"), ("gcode", "geometry"),
          ("render", "analysis", "simulate"), ("pipeline",), ("monitor", "evaluate", "storage"),
          ("farm",), ("cli", "web", "__main__")]
LAYER_OF = {name: k for k, names in enumerate(LAYERS) for name in names}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            out.update(f"{node.module}.{a.name}" for a in node.names)  # `from pkg import module`
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return {m for m in out if m.startswith("layerwatch.")}


def _graph() -> dict[str, set[str]]:
    paths = {_module_name(p): p for p in ROOT.rglob("*.py")}
    return {m: {d for d in _imports(p) if d in paths and d != m} for m, p in paths.items()}


def _package(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_cycles_between_modules():
    graph = _graph()
    # a package's __init__ importing its own submodules is not a cycle of the design
    graph = {m: {d for d in ds if not (d.startswith(m + ".") and m.count(".") == 1)} for m, ds in graph.items()}
    assert _cycles(graph) == []


def test_packages_import_only_lower_layers_and_form_no_cycle():
    pkgs: dict[str, set[str]] = {}
    upward = []
    for m, deps in _graph().items():
        src = _package(m)
        for d in deps:
            dst = _package(d)
            if dst == src:
                continue
            pkgs.setdefault(src, set()).add(dst)
            if LAYER_OF[dst] > LAYER_OF[src]:
                upward.append(f"{m} -> {d}")
    assert upward == []
    assert _cycles(pkgs) == []


def test_the_graph_checker_sees_a_cycle():
    """The checks above can fail: a planted cycle and an upward import are found."""
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert LAYER_OF["web"] > LAYER_OF["evaluate"] > LAYER_OF["pipeline"] > LAYER_OF["analysis"]


def test_one_decision_type_and_a_typed_record():
    from dataclasses import fields

    from layerwatch.analysis.result import LayerResult

    defined = [p for p in ROOT.rglob("*.py") if "class Decision" in p.read_text(encoding="utf-8")]
    assert [p.relative_to(ROOT).as_posix() for p in defined] == ["pipeline/policy.py"]
    assert "extra" not in {f.name for f in fields(LayerResult)}
