"""The README's quick start, as .ci/new_user.py extracts and runs it: the section exists, its substitutions
apply, and every gcdtrav command in it parses with today's CLI (the full run is in CI: .ci/run)."""

from __future__ import annotations

import importlib.util
import shlex
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def new_user_script() -> ModuleType:
    spec = importlib.util.spec_from_file_location("new_user", ROOT / ".ci" / "new_user.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_quick_start_installs_downloads_checks_serves_and_asks() -> None:
    script = new_user_script()
    lines = script.quick_start_lines((ROOT / "README.md").read_text("utf-8"))
    kinds = [
        "install"
        if script.is_install(line)
        else "download"
        if script.download_target(line)
        else "serve"
        if script.is_service(line)
        else shlex.split(line, comments=True)[0]
        for line in lines
    ]
    assert kinds[:2] == ["install", "download"] and "serve" in kinds and kinds[-1] == "gcdtrav", kinds
    assert set(kinds) <= {"install", "download", "serve", "gcdtrav"}, kinds


def test_every_command_uses_the_downloaded_folder_and_parses() -> None:
    from gcdtrav.service.commands.cli import build_parser

    script = new_user_script()
    lines = script.quick_start_lines((ROOT / "README.md").read_text("utf-8"))
    [target] = [t for line in lines if (t := script.download_target(line)) is not None]
    for line in lines:
        words = shlex.split(line, comments=True)
        if words[0] != "gcdtrav":
            continue
        args = build_parser().parse_args(words[1:])  # SystemExit if the README names a flag the CLI lacks
        if hasattr(args, "model") and args.command != "status":
            assert Path(args.model) == target, line  # the tiny checkpoint replaces exactly this folder


def test_the_extraction_refuses_a_readme_without_the_section() -> None:
    import pytest

    script = new_user_script()
    with pytest.raises(SystemExit, match="no <!-- new-user: begin"):
        script.quick_start_lines("# a README\\n```bash\\ngcdtrav serve\\n```\\n")
    with pytest.raises(SystemExit, match="has no --local-dir"):
        script.download_target("hf download CIDAS/clipseg-rd64-refined")
