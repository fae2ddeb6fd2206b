"""`gcdtrav status`'s ground grids: per grid, frames fused and not fused by reason, the newest fused stamp, the
pose stream's age and clock, where each camera's intrinsics and mount come from, the last costmap and speed
mask; below, why a grid fuses nothing (docs/grid.md, *The grid in the status*). Torch-free."""

from __future__ import annotations

from gcdtrav.schemas.messages import GridStatus, ServiceStatus

GRID_ROW = "{:<{w}}  {:<{iw}}  {:<8}  {:>6}  {:>14}  {:>8}  {:>9}  {:>8}  {:>9}  {:>11}  {}"


def _seconds(value: float | None, signed: bool = False) -> str:
    if value is None:
        return "-"
    return f"{value:+.2f}" if signed else f"{value:.1f}"


def _cameras(grid: GridStatus) -> str:
    """'r1/front intrinsics camera_info, mount tf' per camera."""
    return "; ".join(
        f"{name} intrinsics {camera.intrinsics or 'MISSING'}, mount {camera.mount or 'MISSING'}"
        for name, camera in sorted(grid.cameras.items())
    )


def _speed(grid: GridStatus) -> str:
    """The last speed mask's age, 'safe' when it is the floor everywhere (stale grid, stopping instance)."""
    if grid.speed_ago_s is None:
        return "-"
    return f"{grid.speed_ago_s:.1f}" + (" safe" if grid.speed_safe else "")


def grid_lines(statuses: list[ServiceStatus]) -> list[str]:
    """The grids' table (none: no lines), then each grid's frames not fused by reason and why it fuses nothing."""
    rows = [(s.instance, grid) for s in statuses for grid in s.grids or []]
    if not rows:
        return []
    width = max([len("grid"), *(len(grid.source) for _, grid in rows)])
    iwidth = max([len("instance"), *(len(instance) for instance, _ in rows)])
    header = (
        "grid",
        "instance",
        "frame",
        "fused",
        "newest stamp",
        "fused s",
        "pose age s",
        "pose clk",
        "costmap s",
        "speed s",
    )
    lines = ["", GRID_ROW.format(*header, "cameras", w=width, iw=iwidth)]
    problems, not_fused = [], []
    for instance, grid in rows:
        stamp = "-" if grid.newest_fused_stamp is None else f"{grid.newest_fused_stamp:.2f}"
        cells = (grid.frame_id, grid.fused, stamp, _seconds(grid.fused_ago_s), _seconds(grid.pose_age_s),
                 _seconds(grid.pose_clock_s, signed=True), _seconds(grid.costmap_ago_s), _speed(grid))  # fmt: skip
        lines.append(GRID_ROW.format(grid.source, instance, *cells, _cameras(grid), w=width, iw=iwidth))
        if grid.not_fused_by_reason:
            counts = ", ".join(f"{reason} {n}" for reason, n in sorted(grid.not_fused_by_reason.items()))
            not_fused.append(f"  {grid.source} ({instance}): {counts}")
        if grid.problem:
            problems.append(f"  {grid.source} ({instance}): {grid.problem}")
    if not_fused:
        lines += ["", "grid frames not fused:", *not_fused]
    if problems:
        lines += ["", "why a grid fuses nothing:", *problems]
    return lines
