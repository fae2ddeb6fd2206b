"""No import cycles in gcdtrav: every module imports alone, and the static graph (function-local imports
included) has no cycle. `python -m tools.import_graph` prints the same summary."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

from tools.import_graph import build_graph

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
