"""The static import graph of the gcdtrav package: modules, edges, cycles, imports against the layer table.

    python -m tools.import_graph            # summary: modules, edges, cycles, upward imports (exit 1 if any)
    python -m tools.import_graph --edges    # every edge too

Every module belongs to a layer of ``LAYERS`` (the longest prefix that matches); a layer imports only the
layers it lists, so an import of any other layer (a layer above it, or a sibling it has no business with) is
an upward import, reported like a cycle. Every ``import`` statement counts, function-local ones included (a
local import only delays a cycle to the first call: the module imported second sees the first
half-initialised; and an upward import hidden in a function is still upward). ``from a.b import c`` is an edge
to ``a.b.c`` when that is a module, else to ``a.b``. A package is not counted as imported by its own
submodules: Python initialises the parent first, and a package's ``__init__`` importing its children is
the normal shape, not a cycle. Only edges inside gcdtrav are kept.
"""

from __future__ import annotations

import argparse
import ast
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE_ROOTS = ("schemas", "client", "service")  # folders mapped to gcdtrav.<name> by setup.py

# The layer table (docs/architecture.md#layers): each layer and the layers it may import. The service's layers
# stack schemas < engine < backends < pipeline < runtime < experience < bus < commands, with grid, ros and eval
# beside them; the client stands apart and imports only schemas (it runs on a robot without torch); only the
# commands, the top, import the client (`gcdtrav` dispatches the client's commands too).
_SCHEMAS = "gcdtrav.schemas"
_ENGINE, _BACKENDS, _PIPELINE = "gcdtrav.service.engine", "gcdtrav.service.backends", "gcdtrav.service.pipeline"
_GRID, _ROS, _EVAL = "gcdtrav.service.grid", "gcdtrav.service.ros", "gcdtrav.service.eval"
_RUNTIME, _BUS = "gcdtrav.service.runtime", "gcdtrav.service.bus"
_EXPERIENCE = "gcdtrav.service.experience"
_STORE = "gcdtrav.service.store"  # what the fleet remembers (pairs, anchor history): below runtime, zenoh-free
# runtime/ inside, bottom up: the records every room shares (a query's error, the history and its answers, the
# grids, a frame's record by stage), the schedule, the counters, the fleet beside the frame's order, then the
# frame's order: intake (offers to the schedule), triage (glances at what the schedule picked). The worker,
# outputs, status and assembly stay at runtime/'s top and import the rooms.
_RT_ERRORS, _RT_HISTORY, _RT_QUERIES = (f"{_RUNTIME}.{name}" for name in ("errors", "history", "queries"))
_RT_GRIDS, _RT_FRAMES, _RT_STATS = (f"{_RUNTIME}.{name}" for name in ("grids", "frames", "stats"))
_RT_SCHEDULE, _RT_FLEET = f"{_RUNTIME}.schedule", f"{_RUNTIME}.fleet"
_RT_INTAKE, _RT_TRIAGE = f"{_RUNTIME}.intake", f"{_RUNTIME}.triage"
_RT_RECORDS = frozenset({_RT_ERRORS, _RT_HISTORY, _RT_QUERIES, _RT_GRIDS, _RT_FRAMES})
_RT_ROOMS = _RT_RECORDS | {_RT_SCHEDULE, _RT_STATS, _RT_FLEET, _RT_INTAKE, _RT_TRIAGE}
_RUNTIME_ALL = _RT_ROOMS | {_RUNTIME}
_BELOW_RUNTIME = frozenset({_SCHEMAS, _ENGINE, _BACKENDS, _PIPELINE, _GRID, _ROS, _STORE})
LAYERS: dict[str, frozenset[str]] = {
    _SCHEMAS: frozenset(),
    "gcdtrav.service": frozenset({_SCHEMAS}),  # the package's own __init__
    _ENGINE: frozenset({_SCHEMAS}),
    _BACKENDS: frozenset({_SCHEMAS, _ENGINE}),
    _PIPELINE: frozenset({_SCHEMAS, _ENGINE, _BACKENDS}),
    _GRID: frozenset({_SCHEMAS, _ENGINE}),
    _ROS: frozenset({_SCHEMAS, _GRID}),
    _EVAL: frozenset({_SCHEMAS, _ENGINE, _BACKENDS}),
    _STORE: frozenset({_SCHEMAS}),
    _RT_ERRORS: frozenset(),
    _RT_HISTORY: frozenset({_SCHEMAS, _RT_ERRORS}),
    _RT_QUERIES: frozenset({_SCHEMAS, _ENGINE, _RT_ERRORS, _RT_HISTORY}),
    _RT_GRIDS: frozenset({_SCHEMAS, _GRID, _ROS, _RT_ERRORS, _RT_HISTORY, _RT_QUERIES}),
    _RT_FRAMES: frozenset({_SCHEMAS, _PIPELINE, _ROS, _RT_HISTORY, _RT_GRIDS}),
    _RT_SCHEDULE: frozenset({_SCHEMAS}),
    _RT_STATS: frozenset({_SCHEMAS, _RT_SCHEDULE}),  # a source's queue counters and share, for its status
    _RT_FLEET: frozenset({_SCHEMAS, _PIPELINE, _STORE, _RT_FRAMES, _RT_STATS}),
    _RT_INTAKE: frozenset({_SCHEMAS, _ROS, _RT_FRAMES, _RT_SCHEDULE, _RT_STATS}),  # credit words: schemas
    _RT_TRIAGE: frozenset({_SCHEMAS, _RT_FRAMES, _RT_SCHEDULE, _RT_STATS}),
    _RUNTIME: _BELOW_RUNTIME | _RT_ROOMS,
    _EXPERIENCE: frozenset({_SCHEMAS, _ENGINE, _BACKENDS, _GRID, _ROS, _EVAL, _STORE}) | _RUNTIME_ALL,
    _BUS: frozenset({_SCHEMAS, _ENGINE, _BACKENDS, _PIPELINE, _GRID, _ROS, _EXPERIENCE, _STORE}) | _RUNTIME_ALL,
    "gcdtrav.service.commands": frozenset(
        {_SCHEMAS, _ENGINE, _BACKENDS, _PIPELINE, _GRID, _ROS, _EVAL, _EXPERIENCE, _BUS, _STORE, "gcdtrav.client"}
    )
    | _RUNTIME_ALL,
    "gcdtrav.client": frozenset({_SCHEMAS}),
}


def layer_of(module: str) -> str | None:
    """The layer of a module: the longest layer name that is the module or one of its packages."""
    matches = [layer for layer in LAYERS if module == layer or module.startswith(layer + ".")]
    return max(matches, key=len) if matches else None


@dataclass(frozen=True)
class ImportGraph:
    modules: dict[str, Path]
    edges: dict[str, set[str]]

    @property
    def edge_count(self) -> int:
        return sum(len(targets) for targets in self.edges.values())

    def upward_imports(self) -> list[str]:
        """Every import of a layer the importer's layer does not list, and every module outside the table."""
        found = []
        for module in sorted(self.edges):
            layer = layer_of(module)
            if layer is None:
                found.append(f"{module} is in no layer of the table (tools/import_graph.py LAYERS)")
                continue
            for target in sorted(self.edges[module]):
                target_layer = layer_of(target)
                if target_layer != layer and target_layer not in LAYERS[layer]:
                    found.append(f"{module} -> {target} ({layer} may not import {target_layer})")
        return found

    def cycles(self) -> list[list[str]]:
        """The strongly connected components of more than one module, sorted."""
        return sorted(sorted(c) for c in strongly_connected(self.edges) if len(c) > 1)

    def summary(self, with_edges: bool = False) -> str:
        cycles, upward = self.cycles(), self.upward_imports()
        lines = [
            f"gcdtrav import graph: {len(self.modules)} modules, {self.edge_count} edges, {len(cycles)} cycles, "
            f"{len(upward)} upward imports"
        ]
        for cycle in cycles:
            inner = [f"{a} -> {b}" for a in cycle for b in sorted(self.edges[a]) if b in cycle]
            lines.append(f"  cycle of {len(cycle)}: " + "; ".join(inner))
        lines.extend(f"  upward: {problem}" for problem in upward)
        if with_edges:
            for module in sorted(self.edges):
                for target in sorted(self.edges[module]):
                    lines.append(f"  {module} -> {target}")
        return "\n".join(lines)


def package_modules(root: Path = ROOT) -> dict[str, Path]:
    """gcdtrav.<folder>.<...> -> file, for every .py below the package roots."""
    modules = {}
    for folder in PACKAGE_ROOTS:
        for path in sorted((root / folder).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join(["gcdtrav", *parts])] = path
    return modules


def imported_modules(path: Path, module: str, modules: dict[str, Path]) -> set[str]:
    """The gcdtrav modules the file's import statements load: ``from a.b import c`` loads ``a.b.c`` when that
    is a module, else ``a.b``; importing ``a.b.c`` also runs the ``__init__`` of its packages ``a.b`` (not
    counted for the importer's own packages, which Python initialises before it)."""
    tree = ast.parse(path.read_text("utf-8"), str(path))
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    named: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            named.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package[: len(package) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            for alias in node.names:
                named.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base)
    loaded: set[str] = set()
    for name in named:
        parts = name.split(".")
        loaded.update(".".join(parts[:end]) for end in range(2, len(parts) + 1))
    own_packages = {".".join(module.split(".")[:end]) for end in range(1, len(module.split(".")) + 1)}
    return {name for name in loaded if name in modules and name not in own_packages}


def build_graph(root: Path = ROOT) -> ImportGraph:
    modules = package_modules(root)
    edges = {module: imported_modules(path, module, modules) for module, path in modules.items()}
    return ImportGraph(modules, edges)


def strongly_connected(edges: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's algorithm, iterative (no recursion limit on long chains)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    components: list[list[str]] = []
    counter = 0
    for start in sorted(edges):
        if start in index:
            continue
        work = [(start, iter(sorted(edges[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            advanced = False
            for child in children:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges.get(child, set())))))
                    advanced = True
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            if advanced:
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                components.append(component)
    return components


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--edges", action="store_true", help="list every edge")
    args = parser.parse_args(argv)
    graph = build_graph()
    print(graph.summary(with_edges=args.edges))
    return 1 if graph.cycles() or graph.upward_imports() else 0


if __name__ == "__main__":
    sys.exit(main())
