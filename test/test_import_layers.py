"""The import graph: no circles anywhere, and every layer imports only the layers below it.

The imports of every module of the package, of ``bench/`` and of ``launch_scripts/`` are read with
:mod:`ast` -- at the top of a file and inside functions alike -- and resolved to the modules of this
repository (``from mpm_monitor.io import bags`` is an import of the module ``mpm_monitor.io.bags``;
``from mpm_monitor.core.model import PlantModel`` one of ``mpm_monitor.core.model``).

The layers of the package, from the bottom up (docs/architecture.md):

========  ====================================
layer     may import (of the package)
========  ====================================
core      core
sim       core, sim
io        core, sim, io
monitor   core, sim, io, monitor
nodes     core, sim, io, monitor, nodes
apps      everything
========  ====================================

The root module ``mpm_monitor`` imports nothing of the package and anything may import it;
nothing in the package imports ``bench`` or ``launch_scripts``.
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TREES = ("mpm_monitor", "bench", "launch_scripts")

LAYERS = ("core", "sim", "io", "monitor", "nodes", "apps")
ALLOWED = {
    "core": {"core"},
    "sim": {"core", "sim"},
    "io": {"core", "sim", "io"},
    "monitor": {"core", "sim", "io", "monitor"},
    "nodes": {"core", "sim", "io", "monitor", "nodes"},
    "apps": set(LAYERS),
}


def module_files(root: Path = ROOT) -> dict:
    """``{dotted module name: (path, is_package)}`` of every Python file of :data:`TREES`."""
    out = {}
    for tree in TREES:
        for path in sorted((root / tree).rglob("*.py")):
            if "__pycache__" in path.parts:
                continue
            parts = path.relative_to(root).with_suffix("").parts
            is_package = parts[-1] == "__init__"
            if is_package:
                parts = parts[:-1]
            out[".".join(parts)] = (path, is_package)
    return out


def _resolve_base(module: str, is_package: bool, level: int, name) -> str:
    """The absolute module named by ``from <level dots><name> import ...`` inside ``module``."""
    if level == 0:
        return name or ""
    package = module if is_package else module.rpartition(".")[0]
    for _ in range(level - 1):
        package = package.rpartition(".")[0]
    return f"{package}.{name}" if name else package


def _known(name: str, modules: dict, importer: str):
    """The module of this repository an absolute import name means, or None (a third-party one)."""
    if importer.startswith("launch_scripts.") and f"launch_scripts.{name}" in modules:
        return f"launch_scripts.{name}"   # the launch scripts import their neighbours by bare name
    while name:
        if name in modules:
            return name
        name = name.rpartition(".")[0]
    return None


def import_graph(root: Path = ROOT) -> dict:
    """``{module: {imported module: first line}}`` over the modules of :data:`TREES`."""
    modules = module_files(root)
    graph = {}
    for module, (path, is_package) in modules.items():
        edges = graph.setdefault(module, {})
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _resolve_base(module, is_package, node.level, node.module)
                for alias in node.names:
                    sub = f"{base}.{alias.name}"
                    targets.append(sub if sub in modules else base)
            for name in targets:
                target = _known(name, modules, module)
                if target is not None and target != module:
                    edges.setdefault(target, node.lineno)
    return graph


def circles(graph: dict) -> list:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def _describe(component: list, graph: dict, modules: dict) -> str:
    members = set(component)
    lines = [f"import circle of {len(component)} modules: {', '.join(component)}"]
    for a in component:
        path = modules[a][0].relative_to(ROOT)
        for b, line in sorted(graph[a].items()):
            if b in members:
                lines.append(f"    {a} -> {b}  ({path}:{line})")
    return "\n".join(lines)


def layer_of(module: str):
    """The package layer of a module (``mpm_monitor.io.bags.read`` -> ``io``); None outside the layers."""
    parts = module.split(".")
    if parts[0] == "mpm_monitor" and len(parts) > 1 and parts[1] in LAYERS:
        return parts[1]
    return None


def layer_violations(graph: dict, modules: dict) -> list:
    """One line per import that breaks the layer rule, naming the file, the line and the import."""
    bad = []
    for module in sorted(graph):
        path = modules[module][0].relative_to(ROOT)
        in_package = module.split(".")[0] == "mpm_monitor"
        layer = layer_of(module)
        for target, line in sorted(graph[module].items()):
            where = f"{path}:{line}: {module} imports {target}"
            tree = target.split(".")[0]
            if in_package and tree != "mpm_monitor":
                bad.append(f"{where}: the package must not import {tree}/")
            elif module == "mpm_monitor" and tree == "mpm_monitor":
                bad.append(f"{where}: the root module imports nothing of the package")
            elif layer is not None and tree == "mpm_monitor":
                target_layer = layer_of(target)
                if target_layer is None and target != "mpm_monitor":
                    bad.append(f"{where}: {layer} may import only the layers {sorted(ALLOWED[layer])}")
                elif target_layer is not None and target_layer not in ALLOWED[layer]:
                    bad.append(f"{where}: {layer} may import only {', '.join(sorted(ALLOWED[layer]))}, "
                               f"not {target_layer}")
    return bad


# ------------------------------------------------------------------------------------------ tests
def test_the_walk_sees_the_tree():
    graph = import_graph()
    for module in ("mpm_monitor.core.model", "mpm_monitor.io.bags.read", "bench.perf",
                   "launch_scripts.suite_inprocess"):
        assert module in graph, module
    assert "mpm_monitor.io.csv_log" in graph["mpm_monitor.io.bags.read"]           # from ..csv_log import
    assert "mpm_monitor.io.bags" in graph["mpm_monitor.apps.cli"]                   # inside a function
    assert "mpm_monitor.apps.launchers.suite_inprocess" in graph["launch_scripts.suite_inprocess"]  # a script
    assert "mpm_monitor.io.plots" in graph["mpm_monitor.io.report"]                 # from . import plots


def test_the_checks_find_a_planted_circle_and_a_layer_break():
    graph = {"a": {"b": 1}, "b": {"c": 2}, "c": {"a": 3}, "d": {"a": 4}}
    assert circles(graph) == [["a", "b", "c"]]
    fake = {m: (ROOT / "x.py", False) for m in ("mpm_monitor.core.x", "mpm_monitor.io.y")}
    assert len(layer_violations({"mpm_monitor.core.x": {"mpm_monitor.io.y": 7}}, fake)) == 1
    assert layer_violations({"mpm_monitor.io.y": {"mpm_monitor.core.x": 7}}, fake) == []


def test_no_import_circles():
    graph = import_graph()
    modules = module_files()
    found = circles(graph)
    assert not found, "\n" + "\n".join(_describe(c, graph, modules) for c in found)


def test_every_layer_imports_only_the_layers_below_it():
    bad = layer_violations(import_graph(), module_files())
    assert not bad, "\n" + "\n".join(bad)
