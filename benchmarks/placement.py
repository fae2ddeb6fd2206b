"""Where the ground grid puts a hazard while the robot drives (issue 40 item 5): placement, not speed.

    python -m benchmarks.placement                       # every scenario, 5 seeds; prints a Markdown table
    python -m benchmarks.placement --out benchmarks/placement-mine.json
    python -m benchmarks.placement --quick               # 1 seed: a smoke check

A robot drives a synthetic world (tools/synthetic_scene.py: a 1 m square of water at known coordinates on
paved ground, the backend's softmax weights exact) at 0.5, 1 and 2 m/s, straight and turning at 0.5 rad/s,
publishing its pose at 50 Hz and a frame at 5 Hz for 3 s; each frame reaches fusion 0.5-1.5 s after capture
(uniform). The hazard sits 3.5 m ahead of where the drive ends. Time is simulated: the grid (GridOutputs, no
zenoh) gets every pose stamped up to a frame's fusion time before that frame, as the service would. Two ways
to fuse:

- before: each frame projected from the latest pose (what the service did before issue 40);
- after: from the pose at the frame's capture stamp (the pose buffer, service/grid/poses.py).

Measured in the published grid (GridMessage decoded by the client) after the last frame: the cells with
T < 0.5 (the hazard's), their centroid against the hazard's centre and their area against 1 m^2.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import sys
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from gcdtrav.client import Grid
from gcdtrav.schemas.messages import Pose2D
from gcdtrav.schemas.settings import GridSettings
from gcdtrav.service.backends.cpus import cpu_name
from gcdtrav.service.grid.geometry import CameraMount, PinholeCamera
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.runtime.history import FrameRecord

from tools.loopback import grid_update
from tools.synthetic_scene import Hazard, SceneCamera, hazard_view, start_anchors

SPEEDS = (0.5, 1.0, 2.0)
TURN_RATES = (0.0, 0.5)
POSE_HZ, FRAME_HZ = 50.0, 5.0
LATENCY_S = (0.5, 1.5)
DRIVE_S, AHEAD_M = 3.0, 3.5
RESOLUTION_M = 0.1
CAMERA = "robot/cam"


def scene_camera() -> SceneCamera:
    """A 160 x 120 camera, 1 m up, looking 0.35 rad down: one map patch per pixel."""
    return SceneCamera(PinholeCamera(125.0, 125.0, 80.0, 60.0, 160, 120), CameraMount(z=1.0, pitch=0.35), 8.0)


def grid_settings(scene: SceneCamera) -> GridSettings:
    return scene.grid_settings(
        source=CAMERA, pose_key="robot/pose", size_m=20.0, resolution_m=RESOLUTION_M, half_life_s=2.0, max_age_s=None
    )


def unicycle(speed: float, turn_rate: float) -> Callable[[float], tuple[float, float, float]]:
    """The pose (x, y, yaw) at time t of a robot starting at the origin heading +x."""

    def pose(t: float) -> tuple[float, float, float]:
        if turn_rate == 0.0:
            return speed * t, 0.0, 0.0
        radius = speed / turn_rate
        return radius * math.sin(turn_rate * t), radius * (1 - math.cos(turn_rate * t)), turn_rate * t

    return pose


def hazard_ahead(pose: tuple[float, float, float], ahead_m: float = AHEAD_M) -> Hazard:
    x, y, yaw = pose
    return Hazard(x + ahead_m * math.cos(yaw), y + ahead_m * math.sin(yaw))


def drive(
    path: Callable[[float], tuple[float, float, float]],
    hazard: Hazard,
    latencies: list[float],
    at_capture: bool,
    frame_hz: float = FRAME_HZ,
) -> Grid:
    """Frames captured at ``frame_hz`` from t = 0 (one per latency, each reaching fusion that much later),
    poses at POSE_HZ up to each fusion; the grid as published after the last frame."""
    scene, anchors = scene_camera(), start_anchors()
    clock = [0.0]
    grids = GridOutputs([grid_settings(scene)], len(anchors), "placement", clock=lambda: clock[0])
    frames = sorted((k / frame_hz + latency, k / frame_hz) for k, latency in enumerate(latencies))
    next_pose, update = 0, None
    for fused_at, captured in frames:
        while next_pose / POSE_HZ <= fused_at + 1e-9:
            x, y, yaw = path(next_pose / POSE_HZ)
            grids.add_pose(CAMERA, Pose2D(stamp=next_pose / POSE_HZ, frame_id="odom", x=x, y=y, yaw=yaw))
            next_pose += 1
        clock[0] = fused_at
        # before: the latest pose, as if the frame were taken when it is fused; after: its capture stamp
        stamp = captured if at_capture else (next_pose - 1) / POSE_HZ
        weights = hazard_view(scene, hazard, path(captured), anchors.concepts).astype(np.float16)
        size = (scene.camera.width, scene.camera.height)
        update = grid_update(grids, CAMERA, FrameRecord(0, stamp, "", weights, anchors, size), weights)
    assert update is not None, "no frame was fused"
    return Grid.from_payload(update.message.pack())


def hazard_cells(grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """Centres (x, y) of the known cells with T < 0.5."""
    i, j = np.nonzero(np.nan_to_num(grid.traversability, nan=1.0) < 0.5)
    r, (ox, oy) = grid.header.resolution, grid.header.origin
    return ox + (j + 0.5) * r, oy + (i + 0.5) * r


@dataclass(frozen=True)
class Placement:
    speed_mps: float
    turn_rate: float
    fused_at: str  # "latest pose" (before) or "capture pose" (after)
    centroid_error_m: float
    centroid_error_cells: float
    area_m2: float
    truth_area_m2: float


def place(speed: float, turn_rate: float, at_capture: bool, seed: int) -> Placement:
    path = unicycle(speed, turn_rate)
    hazard = hazard_ahead(path(DRIVE_S))
    rng = np.random.default_rng(seed)
    latencies = list(rng.uniform(*LATENCY_S, int(DRIVE_S * FRAME_HZ) + 1))
    grid = drive(path, hazard, latencies, at_capture)
    x, y = hazard_cells(grid)
    error = math.hypot(float(x.mean()) - hazard.x, float(y.mean()) - hazard.y) if len(x) else math.inf
    r = grid.header.resolution
    return Placement(
        speed, turn_rate, "capture pose" if at_capture else "latest pose", error, error / r, len(x) * r * r,
        hazard.side_m**2,
    )  # fmt: skip


def run(seeds: int) -> list[dict[str, float | str]]:
    """Per scenario and way to fuse: the median and worst over ``seeds`` latency draws."""
    rows: list[dict[str, float | str]] = []
    for turn_rate in TURN_RATES:
        for speed in SPEEDS:
            for at_capture in (False, True):
                found = [place(speed, turn_rate, at_capture, seed) for seed in range(seeds)]
                errors = [p.centroid_error_cells for p in found]
                rows.append(
                    {
                        **{k: v for k, v in asdict(found[0]).items() if k in ("speed_mps", "turn_rate", "fused_at")},
                        "centroid_error_cells_median": statistics.median(errors),
                        "centroid_error_cells_max": max(errors),
                        "centroid_error_m_median": statistics.median(p.centroid_error_m for p in found),
                        "area_m2_median": statistics.median(p.area_m2 for p in found),
                        "truth_area_m2": found[0].truth_area_m2,
                    }
                )
    return rows


def table(rows: list[dict[str, float | str]]) -> str:
    lines = [
        "| motion | speed m/s | fused at | centroid error, cells (median / max) | m (median) | area m² (truth 1) |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        motion = "straight" if row["turn_rate"] == 0 else f"turning {row['turn_rate']} rad/s"
        lines.append(
            f"| {motion} | {row['speed_mps']} | {row['fused_at']} | {row['centroid_error_cells_median']:.2f} / "
            f"{row['centroid_error_cells_max']:.2f} | {row['centroid_error_m_median']:.2f} | "
            f"{row['area_m2_median']:.2f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.placement", description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=5, help="latency draws per scenario [5]")
    parser.add_argument("--quick", action="store_true", help="1 seed: a smoke check")
    parser.add_argument("--out", type=Path, help="write the rows and the machine as JSON")
    args = parser.parse_args(argv)
    rows = run(1 if args.quick else args.seeds)
    print(f"cpu: {cpu_name()}, python {platform.python_version()}")
    print(table(rows))
    if args.out is not None:
        args.out.write_text(json.dumps({"cpu": cpu_name(), "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
