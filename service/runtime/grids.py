"""Ground grids on the bus: per configured source, project each frame's anchor weights onto the ground,
fuse them, publish the grid, and answer cell and path queries in metres.

Keys, for a source with a grid:
  {prefix}/out/{source}/grid                      GridMessage (msgpack)
  {prefix}/out/{source}/grid/occupancy            nav_msgs/OccupancyGrid CDR, cost = 100 (1 - T), unknown -1
  {prefix}/out/{source}/grid/uncertainty          nav_msgs/OccupancyGrid CDR, 100 U / 0.5, unknown -1
  {prefix}/out/{source}/cell?x=..;y=..            ContextDistribution of the cell (grid frame, metres)
  {prefix}/out/{source}/cell?path=x0,y0;x1,y1;..  PathReply: the known cells along the polyline
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.images import encode_count_png, encode_map_png16
from gcdtrav.schemas.messages import ContextDistribution, GridHeader, GridMessage, PathReply, Pose2D
from gcdtrav.schemas.settings import GridSettings, RiskSettings
from gcdtrav.service.grid.fusion import GridSpec, GroundGrid
from gcdtrav.service.grid.geometry import CameraMount, PinholeCamera, depth_points, ground_points, map_cell_pixels
from gcdtrav.service.ros.cdr import decode_camera_info, decode_depth, decode_pose, occupancy_cdr
from gcdtrav.service.runtime.errors import QueryError
from gcdtrav.service.runtime.history import FrameRecord
from gcdtrav.service.runtime.queries import (
    RISK_PARAMETERS,
    RiskLevels,
    distribution_of,
    parameter_pairs,
    parse_number,
    risk_levels,
    strict_parameters,
    with_risk,
)
from numpy.typing import NDArray

log = logging.getLogger("gcdtrav.service")
CELL_FORMS = (
    "x=..;y=.. (metres, grid frame), or path=x0,y0;x1,y1;..., and optionally alpha=.. (0 < alpha <= 1), tau=.. "
    "(0 <= tau <= 1)"
)
MAX_PATH_POINTS = 256


@dataclass
class SourceGrid:
    """One source's grid and what it needs besides the maps: camera, mount, latest pose and depth."""

    config: GridSettings
    grid: GroundGrid
    camera: PinholeCamera | None = None
    pose: Pose2D | None = None
    depth: NDArray[np.float32] | None = None
    seq: int = -1

    def __post_init__(self) -> None:
        self.lock = threading.Lock()
        self.mount = CameraMount(**self.config.mount.model_dump())
        if self.config.intrinsics is not None and self.camera is None:
            self.camera = PinholeCamera(**self.config.intrinsics.model_dump())
        self._ground_cache: dict[tuple[Any, ...], tuple[NDArray[np.float64], NDArray[np.bool_]]] = {}

    def camera_for(self, image_size: tuple[int, int]) -> PinholeCamera:
        """Intrinsics scaled to the incoming image's size."""
        camera = self.camera
        if camera is None:
            raise QueryError(f"no intrinsics for '{self.config.source}' yet (waiting for CameraInfo)")
        sx, sy = image_size[0] / camera.width, image_size[1] / camera.height
        return PinholeCamera(camera.fx * sx, camera.fy * sy, camera.cx * sx, camera.cy * sy, *image_size)

    def base_points(self, map_shape: tuple[int, int], image_size: tuple[int, int]):  # type: ignore[no-untyped-def]
        """Ground (or depth) points in the base frame of every map patch, and which patches have one."""
        camera = self.camera_for(image_size)
        u, v = map_cell_pixels(map_shape, image_size)
        if self.depth is not None:
            depth = np.asarray(cv2.resize(self.depth, image_size, interpolation=cv2.INTER_NEAREST), np.float32)
            return depth_points(camera, self.mount, u, v, depth, self.config.max_range_m)
        key = (map_shape, image_size, camera)
        if key not in self._ground_cache:  # a fixed camera: the same rays every frame
            self._ground_cache = {key: ground_points(camera, self.mount, u, v, self.config.max_range_m)}
        return self._ground_cache[key]

    def fuse(self, weights: NDArray[np.floating], image_size: tuple[int, int], stamp: float, anchors: AnchorSet) -> int:
        points, valid = self.base_points((weights.shape[1], weights.shape[2]), image_size)
        flat = weights.reshape(weights.shape[0], -1)[:, valid].astype(np.float32)
        ground = points[valid]
        if self.pose is not None:  # into the odometry frame, and keep the robot at the grid's centre
            c, s = math.cos(self.pose.yaw), math.sin(self.pose.yaw)
            ground = ground @ np.array([[c, s], [-s, c]]) + np.array([self.pose.x, self.pose.y])
            half = self.grid.spec.cells * self.grid.spec.resolution_m / 2
            self.grid.scroll_to((self.pose.x - half, self.pose.y - half))
        landed = self.grid.add(ground, flat, stamp, anchors)
        self.seq += 1
        return landed


@dataclass(frozen=True)
class GridUpdate:
    """One frame's grid outputs: the message, and the OccupancyGrid CDRs (cost, uncertainty) if enabled."""

    message: GridMessage
    occupancy: bytes | None = None
    uncertainty: bytes | None = None


class GridOutputs:
    """All configured grids of a service; thread-safe (frames from the worker, queries from zenoh)."""

    def __init__(self, configs: list[GridSettings], anchor_count: int, instance: str) -> None:
        self.instance = instance
        self.sources = {
            c.source: SourceGrid(c, GroundGrid(GridSpec(c.size_m, c.resolution_m, c.half_life_s), anchor_count))
            for c in configs
        }

    def set_pose(self, source: str, payload: bytes) -> None:
        grid = self.sources[source]
        pose = decode_pose(payload, grid.config.pose_format)
        with grid.lock:
            grid.pose = pose

    def set_camera_info(self, source: str, payload: bytes) -> None:
        camera = decode_camera_info(payload)
        grid = self.sources[source]
        with grid.lock:
            grid.camera = camera

    def set_depth(self, source: str, payload: bytes) -> None:
        depth = decode_depth(payload)
        grid = self.sources[source]
        with grid.lock:
            grid.depth = depth

    def on_frame(self, source: str, record: FrameRecord, weights: NDArray[np.floating]) -> GridUpdate | None:
        """Fuse a processed frame into its source's grid; what to publish, or None."""
        grid = self.sources.get(source)
        if grid is None:
            return None
        with grid.lock:
            if grid.camera is None:
                log.warning("grid of %s: no intrinsics yet (waiting for CameraInfo), frame not fused", source)
                return None
            grid.fuse(weights, record.image_size, record.stamp, record.anchors)
            anchors = record.anchors
            t, u, count = grid.grid.layers(np.asarray(anchors.positions), np.asarray(anchors.widths))
            header = self.header(grid, anchors.version)
        message = GridMessage(
            header=header,
            traversability_png=encode_map_png16(np.nan_to_num(t)),
            uncertainty_png=encode_map_png16(np.nan_to_num(u)),
            count_png=encode_count_png(count),
        )
        if not grid.config.occupancy_grid:
            return GridUpdate(message)
        known = count > 0
        return GridUpdate(message, occupancy_cdr(header, 1.0 - t, known), occupancy_cdr(header, u / 0.5, known))

    def header(self, grid: SourceGrid, version: str) -> GridHeader:
        pose = grid.pose
        return GridHeader(
            source=grid.config.source,
            seq=grid.seq,
            stamp=grid.grid.stamp or 0.0,
            frame_id=pose.frame_id if pose is not None else "base_link",
            origin=grid.grid.origin,
            resolution=grid.grid.spec.resolution_m,
            cells=grid.grid.spec.cells,
            robot=(pose.x, pose.y, pose.yaw) if pose is not None else (0.0, 0.0, 0.0),
            anchor_set_version=version,
            resets=grid.grid.resets,
            last_reset=grid.grid.last_reset,
            known_cells=int(grid.grid.known.sum()),
            instance=self.instance,
        )

    # ---- queries -------------------------------------------------------------------------------------
    def answer(
        self, source: str, raw_parameters: str, risk: RiskSettings | None = None
    ) -> ContextDistribution | PathReply:
        """A cell's or a path's distributions, over the anchor set the grid's weights were fused with."""
        grid = self.sources.get(source)
        if grid is None:
            raise QueryError(f"no grid for source '{source}' (grids: {sorted(self.sources)})")
        params, levels = _without_risk_levels(raw_parameters.strip(), risk or RiskSettings())
        with grid.lock:
            anchors = grid.grid.anchors
            if anchors is None:
                raise QueryError(f"the grid of '{source}' has no frame yet")
            if params.startswith("path="):
                return self._path(grid, _points(params[len("path=") :]), anchors, levels)
            values = strict_parameters(parameter_pairs(params), CELL_FORMS)
            if set(values) != {"x", "y"}:
                raise QueryError(f"give {CELL_FORMS}")
            x, y = parse_number(values["x"], "x"), parse_number(values["y"], "y")
            i, j = (int(v) for v in grid.grid.index_of(np.array(x), np.array(y)))
            n = grid.grid.spec.cells
            if not (0 <= i < n and 0 <= j < n):
                lo, hi = (
                    grid.grid.origin,
                    (
                        grid.grid.origin[0] + n * grid.grid.spec.resolution_m,
                        grid.grid.origin[1] + n * grid.grid.spec.resolution_m,
                    ),
                )
                raise QueryError(f"({x:g}, {y:g}) is outside the grid [{lo[0]:g}, {hi[0]:g}) x [{lo[1]:g}, {hi[1]:g})")
            cell = self._cell(grid, i, j, anchors, levels)
            if cell is None:
                raise QueryError(f"cell ({x:g}, {y:g}) is unknown: never observed")
            return cell

    def _cell(
        self, grid: SourceGrid, i: int, j: int, anchors: AnchorSet, levels: RiskLevels
    ) -> ContextDistribution | None:
        weights = grid.grid.cell_weights(i, j)
        if weights is None:
            return None
        weights = weights / weights.sum()
        reply = distribution_of(
            weights,
            anchors,
            grid.config.source,
            None,  # a cell fuses many frames: no one frame's seq
            grid.grid.stamp or 0.0,
            self.header(grid, anchors.version).frame_id,
        )
        return with_risk(reply, weights, anchors, levels).model_copy(
            update={
                "cell": (i, j),
                "cell_xy": grid.grid.centre_of(i, j),
                "observations": int(grid.grid.count[i, j]),
                "grid_updates": grid.seq,
            }
        )

    def _path(
        self, grid: SourceGrid, points: list[tuple[float, float]], anchors: AnchorSet, levels: RiskLevels
    ) -> PathReply:
        cells, unknown = [], 0
        for i, j in grid.grid.path_cells(points):
            cell = self._cell(grid, i, j, anchors, levels)
            if cell is None:
                unknown += 1
            else:
                cells.append(cell)
        below = [cell.p_below or 0.0 for cell in cells]
        return PathReply(
            source=grid.config.source,
            stamp=grid.grid.stamp or 0.0,
            anchor_set_version=anchors.version,
            points=points,
            cells=cells,
            unknown_cells=unknown,
            lowest_t=min(range(len(cells)), key=lambda k: cells[k].mean) if cells else None,
            highest_u=max(range(len(cells)), key=lambda k: cells[k].std) if cells else None,
            lowest_cvar=min(range(len(cells)), key=lambda k: cells[k].cvar or 0.0) if cells else None,
            p_any_below=float(1 - np.prod(1 - np.asarray(below, np.float64))) if cells else None,
            alpha=levels.alpha,
            tau=levels.tau,
        )


def _without_risk_levels(params: str, defaults: RiskSettings) -> tuple[str, RiskLevels]:
    """The cell or path parameters without alpha and tau, and the levels they give: a path's points are
    ';'-separated too, so alpha=.. and tau=.. are taken out wherever they stand."""
    risky = [(name, value) for name, value in parameter_pairs(params) if name in RISK_PARAMETERS]
    rest = ";".join(part for part in params.split(";") if part.split("=", 1)[0] not in RISK_PARAMETERS)
    levels = strict_parameters(risky, CELL_FORMS)
    return rest, risk_levels(levels, defaults)


def _points(text: str) -> list[tuple[float, float]]:
    points = []
    for part in text.split(";"):
        if not part.strip():
            continue
        coordinates = part.split(",")
        if len(coordinates) != 2:
            raise QueryError(f"path point '{part}' must be x,y in metres")
        points.append((parse_number(coordinates[0], "x"), parse_number(coordinates[1], "y")))
    if not 2 <= len(points) <= MAX_PATH_POINTS:
        raise QueryError(f"a path needs 2 to {MAX_PATH_POINTS} points x,y separated by ';', got {len(points)}")
    return points
