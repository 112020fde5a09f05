"""The core's packages import one way (docs/architecture.md, "Layers"): each imports only its own
layer and those below it, nothing in `slamkit` imports a plugin, and the modules' import-time
graph has no cycle. Read from the source with ast, so a lazy import inside a function counts for
the layers too."""

from __future__ import annotations

import ast
from pathlib import Path

import slamkit

ROOT = Path(slamkit.__file__).resolve().parent
#: The layers, bottom up: a package may import its own layer and those below.
LAYERS = [
    {"types", "errors", "tuning", "config", "plugin", "scheduling", "progress"},  # vocabulary
    {"geometry"},
    {"map", "metrics", "formats", "cache", "native", "downloads"},
    {"roles"},
    {"registry"},
    {"run"},
    {"cli"},
]
LEVEL = {name: level for level, names in enumerate(LAYERS) for name in names}


def module_name(path: Path) -> str:
    parts = ("slamkit", *path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path, top_level_only: bool) -> list[tuple[int, str]]:
    """(line, module) of the absolute imports of slamkit and slamkit_plugins in the file (`from
    a.b import c` gives a.b.c as well as a.b: c may be a module); with `top_level_only`, those
    run at import time (not inside a function)."""
    tree = ast.parse(path.read_text(), str(path))
    nodes = ast.walk(tree)
    if top_level_only:
        nodes = [n for stmt in tree.body for n in ast.walk(stmt) if not isinstance(stmt, (ast.FunctionDef,
                                                                                         ast.AsyncFunctionDef))]
        nodes = [n for n in nodes if not isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
    found = []
    for node in nodes:
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found += [(node.lineno, node.module)] + [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
    return [(line, m) for line, m in found if m.split(".")[0] in ("slamkit", "slamkit_plugins")]


SOURCES = sorted(ROOT.rglob("*.py"))


def test_every_package_has_a_layer():
    packages = {module_name(p).split(".")[1] for p in SOURCES if module_name(p) != "slamkit"}
    assert packages <= set(LEVEL), f"packages without a layer: {sorted(packages - set(LEVEL))}"


def test_no_package_imports_a_layer_above_it_and_the_core_no_plugin():
    offending = []
    for path in SOURCES:
        name = module_name(path)
        if name == "slamkit":
            continue
        own = name.split(".")[1]
        for line, module in imports(path, top_level_only=False):
            if module.startswith("slamkit_plugins"):
                offending.append(f"{name}:{line} imports the plugin {module}")
            elif module != "slamkit" and LEVEL[module.split(".")[1]] > LEVEL[own]:
                offending.append(f"{name}:{line} ({own}) imports {module}, a layer above")
    assert not offending, "\n".join(offending)


def test_the_modules_import_time_graph_has_no_cycle():
    modules = {module_name(p): p for p in SOURCES}
    graph = {}
    for name, path in modules.items():
        targets = set()
        found = {module for _, module in imports(path, top_level_only=True)}
        for module in found:
            if any(other.startswith(module + ".") and other in modules for other in found):
                continue  # `from a.b import c` with c a module: the edge is to a.b.c
            while module and module not in modules:  # a name in a module: the module
                module = module.rpartition(".")[0]
            if module and module != name:
                targets.add(module)
        graph[name] = targets
    state, stack, cycles = {}, [], []

    def visit(node: str) -> None:
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == "open":
                cycles.append(" -> ".join(stack[stack.index(nxt):] + [nxt]))
            elif nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node)
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


#: Inside `run`, the algorithm (SLAM and what it calls) imports neither what feeds it frames (the
#: runners and their workers) nor the run around it (the pipeline, outputs, checkpoints); the
#: runners do not import the pipeline. Each room may import the rooms before it.
RUN_ROOMS = [
    ("algorithm", {"slamkit.run.slam", "slamkit.run.handover", "slamkit.run.loop_closing",
                   "slamkit.run.loop_process", "slamkit.run.boundary", "slamkit.run.heap"}),
    ("runners", {"slamkit.run.runner", "slamkit.run.live", "slamkit.run.workers"}),
    ("pipeline", {"slamkit.run.pipeline"}),
]


def test_the_runs_rooms_import_one_way():
    room_of = {module: level for level, (_, modules) in enumerate(RUN_ROOMS) for module in modules}
    sources = {module_name(p): p for p in SOURCES}
    assert set(room_of) <= set(sources), f"rooms list modules that are gone: {sorted(set(room_of) - set(sources))}"
    offending = []
    for module, level in room_of.items():
        for line, imported in imports(sources[module], top_level_only=False):
            target = next((m for m in room_of if imported == m or imported.startswith(m + ".")), None)
            if target is not None and room_of[target] > level:
                offending.append(f"{module}:{line} ({RUN_ROOMS[level][0]}) imports {imported} "
                                 f"({RUN_ROOMS[room_of[target]][0]})")
    assert not offending, "\n".join(offending)
