"""The base install (schemas + client) must work on a planner's machine without torch."""

from __future__ import annotations

import subprocess
import sys
import textwrap


def test_schemas_client_and_engine_import_without_torch() -> None:
    code = textwrap.dedent(
        """
        import sys
        sys.modules["torch"] = None          # any `import torch` now raises ImportError
        sys.modules["transformers"] = None
        import gcdtrav.schemas, gcdtrav.client, gcdtrav.service.engine
        from gcdtrav.schemas import default_anchor_set
        print(default_anchor_set().version)
        """
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert len(result.stdout.strip()) == 16


def test_no_bare_top_level_modules() -> None:
    code = "import importlib.util as u; print([m for m in ('service', 'client', 'schemas') if u.find_spec(m)])"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd="/")
    assert result.stdout.strip() == "[]"


def test_cli_without_torch_says_what_to_install(tmp_path) -> None:  # type: ignore[no-untyped-def]
    code = textwrap.dedent(
        """
        import sys, importlib.util
        real = importlib.util.find_spec
        importlib.util.find_spec = lambda name, *a: None if name == "torch" else real(name, *a)
        from gcdtrav.service.cli import main
        sys.exit(main(["infer", "x.jpg", "--out", "o"]))
        """
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert "needs torch" in result.stderr and "pip install torch==2.13.0" in result.stderr
    assert "Traceback" not in result.stderr
