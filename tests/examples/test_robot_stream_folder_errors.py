"""examples/robot_stream_folder.py on a bad folder: one line on stderr and exit 2, no traceback, before any
zenoh session is opened."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "examples" / "robot_stream_folder.py"


def run(folder: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(SCRIPT), str(folder)], capture_output=True, text=True, timeout=60)


def test_a_missing_folder_is_one_line_and_exit_2(tmp_path: Path) -> None:
    result = run(tmp_path / "nowhere")
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.splitlines() == [f"robot_stream_folder: {tmp_path / 'nowhere'}: no such folder"]


def test_a_folder_without_images_is_one_line_and_exit_2(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("no images here")
    result = run(tmp_path)
    assert result.returncode == 2
    assert result.stderr.splitlines() == [f"robot_stream_folder: {tmp_path}: no .jpg/.jpeg/.png files"]
