"""No import cycles in gcdtrav and no upward import: every module imports alone, and the static graph
(function-local imports included) has no cycle and no import against the layer table (tools/import_graph.py
LAYERS, docs/architecture.md#layers). `python -m tools.import_graph` prints the same summary."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

from tools.import_graph import LAYERS, build_graph, layer_of

ROOT = Path(__file__).resolve().parents[1]


def test_the_static_import_graph_has_no_cycle() -> None:
    graph = build_graph(ROOT)
    assert len(graph.modules) > 50 and graph.edge_count > 100, graph.summary()
    assert graph.cycles() == [], graph.summary()


def test_the_graph_sees_a_cycle_through_a_function_local_import(tmp_path: Path) -> None:
    (tmp_path / "service" / "backends").mkdir(parents=True)
    (tmp_path / "schemas").mkdir()
    (tmp_path / "client").mkdir()
    for package in ("service", "service/backends", "schemas", "client"):
        (tmp_path / package / "__init__.py").write_text("")
    (tmp_path / "service" / "backends" / "a.py").write_text("from gcdtrav.service import b\n")
    (tmp_path / "service" / "b.py").write_text("def f():\n    from .backends.a import x\n")
    graph = build_graph(tmp_path)
    assert graph.edges["gcdtrav.service.b"] == {"gcdtrav.service.backends", "gcdtrav.service.backends.a"}
    assert graph.cycles() == [["gcdtrav.service.b", "gcdtrav.service.backends.a"]]
    assert "1 cycles" in graph.summary() and "gcdtrav.service.b -> gcdtrav.service.backends.a" in graph.summary()


def test_every_import_follows_the_layer_table() -> None:
    graph = build_graph(ROOT)
    assert all(layer_of(module) is not None for module in graph.modules), graph.upward_imports()
    assert graph.upward_imports() == [], graph.summary()


def test_the_layer_table_is_a_hierarchy() -> None:
    """Each layer imports only layers that exist and never itself, and no two layers import each other, even
    through others (the table itself has no cycle)."""
    for layer, allowed in LAYERS.items():
        assert layer not in allowed and allowed <= set(LAYERS), layer
    reachable = {layer: set(allowed) for layer, allowed in LAYERS.items()}
    for _ in LAYERS:
        for layer in reachable:
            reachable[layer] |= {far for near in reachable[layer] for far in reachable[near]}
    assert all(layer not in below for layer, below in reachable.items())
    assert layer_of("gcdtrav.service.runtime.grids.state") == "gcdtrav.service.runtime.grids"
    assert layer_of("gcdtrav.service.runtime.worker") == "gcdtrav.service.runtime"
    assert layer_of("gcdtrav.service.pipeline") == "gcdtrav.service.pipeline"
    assert layer_of("gcdtrav.client.commands.view") == "gcdtrav.client"
    assert layer_of("gcdtrav.elsewhere") is None


def test_runtime_shows_its_rooms_in_the_frames_order() -> None:
    """runtime/ keeps at most 12 loose modules; each room is a layer; the schedule knows nothing of the intake
    that feeds it or the triage after it, and no room imports runtime/'s top (the worker, outputs, assembly)."""
    runtime = ROOT / "service" / "runtime"
    loose = [path.stem for path in runtime.glob("*.py") if path.stem != "__init__"]
    rooms = [path.name for path in runtime.iterdir() if (path / "__init__.py").exists()]
    assert len(loose) <= 12, sorted(loose)
    assert {"intake", "schedule", "triage", "fleet", "grids"} <= set(rooms)
    layer = {room: f"gcdtrav.service.runtime.{room}" for room in rooms}
    assert all(name in LAYERS and "gcdtrav.service.runtime" not in LAYERS[name] for name in layer.values())
    assert layer["schedule"] in LAYERS[layer["intake"]] and layer["schedule"] in LAYERS[layer["triage"]]
    assert not {layer["intake"], layer["triage"]} & LAYERS[layer["schedule"]]


def test_intake_and_triage_import_nothing_of_the_fleet() -> None:
    """The frame's order frees slots (credits) without the fleet: the credit words live in schemas, the frame's
    times in runtime/frames.py. Neither the table nor the code lets intake/ or triage/ reach fleet/."""
    fleet = "gcdtrav.service.runtime.fleet"
    graph = build_graph(ROOT)
    for room in ("intake", "triage"):
        layer = f"gcdtrav.service.runtime.{room}"
        assert fleet not in LAYERS[layer], f"{room} may import the fleet again"
        reached = {target for module in graph.edges if layer_of(module) == layer for target in graph.edges[module]}
        assert not {target for target in reached if layer_of(target) == fleet}, f"{room} imports the fleet"


def _synthetic_tree(root: Path, files: dict[str, str]) -> None:
    for package in ("schemas", "client", "service", "service/backends", "service/runtime", "service/commands"):
        (root / package).mkdir(parents=True, exist_ok=True)
        (root / package / "__init__.py").write_text("")
    for name, text in files.items():
        (root / name).write_text(text)


def test_a_function_local_upward_import_fails_the_table(tmp_path: Path) -> None:
    """A backend reaching up into runtime inside a function: no cycle, but an upward import."""
    _synthetic_tree(
        tmp_path,
        {
            "service/runtime/worker.py": "X = 1\n",
            "service/backends/model.py": "def build():\n    from gcdtrav.service.runtime.worker import X\n",
        },
    )
    graph = build_graph(tmp_path)
    assert graph.cycles() == []
    assert graph.upward_imports() == [
        "gcdtrav.service.backends.model -> gcdtrav.service.runtime "
        "(gcdtrav.service.backends may not import gcdtrav.service.runtime)",
        "gcdtrav.service.backends.model -> gcdtrav.service.runtime.worker "
        "(gcdtrav.service.backends may not import gcdtrav.service.runtime)",
    ]
    assert "1 upward imports" not in graph.summary() and "2 upward imports" in graph.summary()


def test_downward_imports_pass_and_the_client_may_not_import_the_service(tmp_path: Path) -> None:
    _synthetic_tree(
        tmp_path,
        {
            "service/backends/model.py": "X = 1\n",
            "service/commands/run.py": "def main():\n    from gcdtrav.service.backends.model import X\n",
            "client/library.py": "def f():\n    from gcdtrav.service.backends import model\n",
            "service/loose.py": "Y = 2\n",
        },
    )
    problems = build_graph(tmp_path).upward_imports()
    assert not any(problem.startswith("gcdtrav.service.commands") for problem in problems)
    upward = "gcdtrav.client.library -> gcdtrav.service.backends.model"
    assert f"{upward} (gcdtrav.client may not import gcdtrav.service.backends)" in problems
    assert not any("gcdtrav.service.loose" in problem for problem in problems)  # service/__init__'s layer


def test_every_module_imports_alone() -> None:
    """In one fresh interpreter, each module imported with no gcdtrav module loaded before it (third-party
    modules stay loaded: only gcdtrav's own order matters). A module whose optional dependency is not
    installed is reported, not failed."""
    modules = sorted(build_graph(ROOT).modules)
    code = textwrap.dedent(
        """
        import importlib, json, sys, traceback
        failures, missing = {}, {}
        for name in json.loads(sys.argv[1]):
            for loaded in [m for m in sys.modules if m == "gcdtrav" or m.startswith("gcdtrav.")]:
                del sys.modules[loaded]
            try:
                importlib.import_module(name)
            except ModuleNotFoundError as err:
                if err.name and not err.name.startswith("gcdtrav"):
                    missing[name] = err.name
                else:
                    failures[name] = traceback.format_exc(limit=3)
            except Exception:
                failures[name] = traceback.format_exc(limit=3)
        print(json.dumps({"failures": failures, "missing": missing}))
        """
    )
    result = subprocess.run(
        [sys.executable, "-c", code, json.dumps(modules)], capture_output=True, text=True, timeout=300, cwd=ROOT
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report["failures"] == {}, "\n".join(f"{k}:\n{v}" for k, v in report["failures"].items())
    if report["missing"]:
        print("not imported, optional dependency missing:", report["missing"])
