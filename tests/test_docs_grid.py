"""docs/grid.md's top view agrees with the code: row i runs along y, column j along x (it drew row i along x)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

ROOT = Path(__file__).resolve().parents[1]


def top_view() -> list[str]:
    text = (ROOT / "docs" / "grid.md").read_text("utf-8")
    start = text.index("top view (grid frame)")
    return text[start : text.index("```", start)].splitlines()


def test_the_top_view_draws_columns_along_x_and_rows_along_y() -> None:
    from gcdtrav.client.client import Grid
    from gcdtrav.schemas.messages import GridHeader

    lines = top_view()
    horizontal = next(line for line in lines if "──►" in line and "x" not in line.split("──►")[-1])
    assert "column j" in horizontal and "row i" not in horizontal
    assert any(line.rstrip().endswith("│ row i") for line in lines)  # the vertical arrow, along y
    assert "cell (i, j): x ∈ [ox + j r, ox + (j+1) r), y ∈ [oy + i r, oy + (i+1) r)" in "\n".join(lines)
    header = GridHeader(
        source="cam", seq=0, stamp=0.0, frame_id="odom", origin=(10.0, 20.0), resolution=0.5, cells=8,
        anchor_set_version="v", resets=0, known_cells=0, instance="i",
    )  # fmt: skip
    grid = SimpleNamespace(header=header)  # cell_index reads only the header
    assert Grid.cell_index(grid, x=10.0 + 2.5 * 0.5, y=20.0 + 0.5 * 0.5) == (0, 2)  # type: ignore[arg-type]
