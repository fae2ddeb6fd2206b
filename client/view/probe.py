"""The distribution the operator points at: a patch of a source's image maps or a cell of its ground grid,
chosen with the Parameters panel (``probe/*``) or by a published point (a geometry_msgs/PointStamped as JSON:
from a Publish panel, or the 3D panel's "Publish point" tool where the viewer offers it; Lichtblick offers it
for ROS data sources only, see docs/view.md), drawn like `gcdtrav probe --png`.

Parameters:

    probe/source    str     the source; '' = nothing probed
    probe/target    str     'patch' (x, y = pixels of the source's image) or 'cell' (metres in its grid's frame)
    probe/x         float
    probe/y         float
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from typing import Literal

PREFIX = "probe"
TARGETS = ("patch", "cell")
Target = Literal["patch", "cell"]


@dataclass(frozen=True)
class ProbeTarget:
    source: str = ""
    target: Target = "patch"
    x: float = 0.0
    y: float = 0.0

    @property
    def active(self) -> bool:
        return bool(self.source)


def probe_parameters(probe: ProbeTarget) -> dict[str, str | float]:
    return {f"{PREFIX}/source": probe.source, f"{PREFIX}/target": probe.target, f"{PREFIX}/x": probe.x,
            f"{PREFIX}/y": probe.y}  # fmt: skip


def is_probe_parameter(name: str) -> bool:
    return name.startswith(f"{PREFIX}/")


def apply_probe_parameters(probe: ProbeTarget, changes: dict[str, object]) -> ProbeTarget:
    """``probe`` with ``changes`` (probe/* names only); ValueError naming the parameter otherwise."""
    for name, value in changes.items():
        field = name.removeprefix(f"{PREFIX}/")
        if field == "source":
            if not isinstance(value, str):
                raise ValueError(f"{name}: expected text, got {value!r}")
            probe = replace(probe, source=value.strip("/"))
        elif field == "target":
            if value not in TARGETS:
                raise ValueError(f"{name}: expected one of {', '.join(TARGETS)}, got {value!r}")
            probe = replace(probe, target="cell" if value == "cell" else "patch")
        elif field in ("x", "y"):
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
                raise ValueError(f"{name}: expected a finite number, got {value!r}")
            probe = replace(probe, x=float(value)) if field == "x" else replace(probe, y=float(value))
        else:
            raise ValueError(f"{name}: no such parameter; the probe's are {', '.join(probe_parameters(probe))}")
    return probe


@dataclass(frozen=True)
class ClickedPoint:
    frame_id: str
    x: float
    y: float


def clicked_point(data: bytes) -> ClickedPoint:
    """A geometry_msgs/PointStamped (or foxglove.Point3InFrame-like) JSON message; ValueError otherwise."""
    try:
        message = json.loads(data)
        frame_id = str((message.get("header") or {}).get("frame_id") or message.get("frame_id") or "")
        point = message.get("point") or message
        x, y = float(point["x"]), float(point["y"])
    except (ValueError, TypeError, KeyError, AttributeError) as err:
        raise ValueError(f"not a point as JSON: {type(err).__name__}: {err}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f"point ({x}, {y}) is not finite")
    return ClickedPoint(frame_id, x, y)


def to_grid_frame(
    point: ClickedPoint, grid_frame: str, robot: tuple[float, float, float] | None, base_frame: str
) -> tuple[float, float] | None:
    """The point in the grid's frame: as is when given in it, through the robot's pose when given in the
    base frame; None when it cannot be placed."""
    if point.frame_id in ("", grid_frame):
        return point.x, point.y
    if point.frame_id == base_frame and robot is not None:
        rx, ry, yaw = robot
        c, s = math.cos(yaw), math.sin(yaw)
        return rx + c * point.x - s * point.y, ry + s * point.x + c * point.y
    return None
