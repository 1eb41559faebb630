"""The package reads top-down: no import circle, and no import that goes up the layer table.

The table below is the one statement of the layers (docs/architecture.md draws it). Every
import is counted, at module level and inside functions (``ast``), relative or absolute;
``TYPE_CHECKING`` imports too. A module may import its own layer or the layers below it.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: the layers, bottom up; a module belongs to the layer of its longest matching prefix
LAYERS: tuple[tuple[str, ...], ...] = (
    ("arraysel", "arraysel.errors",                         # version, error types,
     "arraysel.selection"),                                 # a selection's representations and checks
    ("arraysel.io",),                                       # atomic writes, cache folder, mask files
    ("arraysel.physics", "arraysel.physics.volume"),        # probes, delays, SIMUS, beamforming, PSF; 3-D
    ("arraysel.scenes",),                                   # the scene schema and built-in scenes
    ("arraysel.objective",),                                # metrics, losses, contract, objectives
    ("arraysel.selectors",),                                # selector contract, hooks, registry, relaxations
    ("arraysel_plugins",),                                  # the built-in selectors (plugins/)
    ("arraysel.report",),                                   # column schema, tables, IOH export, plots
    ("arraysel.run",),                                      # experiments, compare, executors
    ("arraysel.e2e",),                                      # end-to-end training
    ("arraysel.api", "arraysel.testing"),                   # notebook API, conformance suite
    ("arraysel.cli", "arraysel.__main__"),                  # the `arraysel` command, python -m arraysel
)


def _modules() -> dict[str, Path]:
    mods = {}
    for base, pkg in ((ROOT / "arraysel", "arraysel"), (ROOT / "plugins", "arraysel_plugins")):
        for path in base.rglob("*.py"):
            parts = list(path.relative_to(base).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join([pkg, *parts])] = path
    return mods


MODULES = _modules()


def _resolve(name: str) -> str | None:
    """The module ``name`` refers to (``pkg.mod.attr`` -> ``pkg.mod``), if it is ours."""
    while name and name not in MODULES:
        if "." not in name:
            return None
        name = name.rsplit(".", 1)[0]
    return name or None


def imports_of(module: str) -> set[str]:
    path = MODULES[module]
    is_pkg = path.name == "__init__.py"
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_pkg else module.split(".")[:-1]
                base = base[:len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            targets = [f"{mod}.{a.name}" for a in node.names]
        else:
            continue
        for t in targets:
            r = _resolve(t)
            if r is not None and r != module:
                out.add(r)
    return out


GRAPH = {m: imports_of(m) for m in MODULES}


def layer_of(module: str) -> int:
    best, rank = -1, None
    for i, prefixes in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > best:
                best, rank = len(p), i
    assert rank is not None, f"{module} is in no layer of LAYERS: add it to the table"
    return rank


def test_every_module_has_a_layer():
    for m in MODULES:
        layer_of(m)


def test_no_import_goes_up_a_layer():
    up = [f"{m} (layer {LAYERS[layer_of(m)][0]}) imports {t} (layer {LAYERS[layer_of(t)][0]})"
          for m, targets in sorted(GRAPH.items()) for t in sorted(targets) if layer_of(t) > layer_of(m)]
    assert not up, "imports that go up the layer table:\n" + "\n".join(up)


def _cycles() -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in GRAPH[v]:
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

    for v in sorted(GRAPH):
        if v not in index:
            visit(v)
    return out


def test_no_import_circle():
    assert _cycles() == []


def test_the_checks_can_fail():
    """A circle and an upward import planted in a copy of the graph are found."""
    global GRAPH
    saved = GRAPH
    try:
        GRAPH = {m: set(t) for m, t in saved.items()}
        GRAPH["arraysel.errors"].add("arraysel.cli.main")
        GRAPH["arraysel.cli.main"].add("arraysel.errors")
        assert _cycles()
        with pytest.raises(AssertionError, match="arraysel.errors .* imports arraysel.cli.main"):
            test_no_import_goes_up_a_layer()
    finally:
        GRAPH = saved


def test_function_level_imports_are_counted():
    assert "arraysel.run.compare" in GRAPH["arraysel.cli.compare"]      # imported inside run()


def test_the_layer_table_is_the_documented_one():
    doc = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    for prefixes in LAYERS:
        for p in prefixes:
            name = p.replace("arraysel_plugins", "plugins/").replace("arraysel.", "").replace("arraysel", "")
            if name:
                assert name in doc, f"docs/architecture.md does not mention {name}"


def test_no_library_module_uses_the_test_helpers():
    """``arraysel.testing`` is for test authors: the CLI's ``--scene toy`` and the executors use the real
    toy objective (``arraysel.objective.toy``)."""
    users = sorted(m for m, targets in GRAPH.items() if "arraysel.testing" in targets)
    assert users == []


def test_executors_do_not_know_objective_classes():
    """Workers rebuild an objective through its ``worker_factory()`` capability, not by its class."""
    for m in ("arraysel.run.executors", "arraysel.run.workers", "arraysel.run.isolation", "arraysel.run.template",
              "arraysel.run.random_search", "arraysel.run.compare_task", "arraysel.run.compare"):
        assert not {t for t in GRAPH[m] if t.startswith("arraysel.objective.")}, m
        assert "__name__ ==" not in MODULES[m].read_text(encoding="utf-8").replace("if __name__", "")
