"""The base install (schemas + client) must work on a planner's machine without torch."""

from __future__ import annotations

import importlib.metadata
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest


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
        from gcdtrav.service.commands.cli import main
        sys.exit(main(["infer", "x.jpg", "--out", "o"]))
        """
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert "needs torch" in result.stderr and "pip install torch==2.13.0" in result.stderr
    assert "Traceback" not in result.stderr


ROOT = Path(__file__).resolve().parent.parent
PACKAGE_ROOTS = ("schemas", "client", "service")


def test_installed_wheel_has_every_module_data_file_and_the_license() -> None:
    """CI installs the built wheel: every file under schemas/, client/ and service/ must be in it."""
    import gcdtrav.schemas

    module = Path(gcdtrav.schemas.__file__).resolve()
    if module.parent.parent.name != "gcdtrav":  # <checkout>/schemas/__init__.py, this checkout's or another's
        pytest.skip("editable install: the package files are a checkout's (CI tests the built wheel)")
    site = [str(module.parents[2])]  # site-packages/gcdtrav/schemas/__init__.py
    (distribution,) = [d for d in importlib.metadata.distributions(path=site) if d.name == "gcdtrav"]
    files = {str(path) for path in distribution.files or () if Path(str(distribution.locate_file(path))).exists()}
    expected = {
        f"gcdtrav/{path.relative_to(ROOT).as_posix()}"
        for root in PACKAGE_ROOTS
        for path in (ROOT / root).rglob("*")
        if path.is_file() and "__pycache__" not in path.parts
    }
    assert not expected - files, f"missing from the wheel: {sorted(expected - files)}"
    assert any(name.endswith("licenses/LICENSE") for name in files)


def test_docker_image_and_ci_install_the_wheel_with_the_same_command() -> None:
    def install_steps(text: str) -> list[str]:
        return [" ".join(m.split()) for m in re.findall(r"(sh deploy/install-wheel\.sh [^&\n]+)", text)]

    ci = install_steps((ROOT / ".ci" / "run").read_text())
    docker = install_steps((ROOT / "deploy" / "Dockerfile").read_text())
    assert len(ci) == len(docker) == 1 and ci == docker, (ci, docker)
    assert "--from=wheel" in (ROOT / "deploy" / "Dockerfile").read_text()  # the wheel built in the first stage
