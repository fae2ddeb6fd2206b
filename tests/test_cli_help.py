"""`gcdtrav --help` and `gcdtrav view --help` speak to users: no module paths, the current way to get a layout."""

from __future__ import annotations

import re

import pytest
from gcdtrav.service.commands.cli import build_parser


def help_of(*args: str, capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as done:
        build_parser().parse_args([*args, "--help"])
    assert done.value.code == 0
    return capsys.readouterr().out


def test_the_top_help_names_commands_not_module_paths(capsys: pytest.CaptureFixture[str]) -> None:
    text = " ".join(help_of(capsys=capsys).split())
    assert not re.search(r"gcdtrav\.(client|service|schemas)\.", text), text
    assert "gcdtrav doctor" in text and "COMMAND --help" in text


def test_view_help_recommends_the_generated_layout(capsys: pytest.CaptureFixture[str]) -> None:
    text = " ".join(help_of("view", capsys=capsys).split())
    assert "gcdtrav view --layout my-layout.json" in text
    assert "gcdtrav-layout.json" not in text  # the older fixed layout of one source 'cam'
