"""Ground grids on the bus: per configured grid, project each frame of its cameras onto the ground, fuse
them, publish the grid and its layers, and answer cell and path queries in metres.

Keys, for a grid published under {source} (its single camera's source, or its name; docs/grid.md):
  {prefix}/out/{source}/grid                      GridMessage (msgpack): T, U, counts, CVaR, p_below, match, age
  {prefix}/out/{source}/grid/occupancy            nav_msgs/OccupancyGrid CDR, cost = 100 (1 - T), unknown -1
  {prefix}/out/{source}/grid/uncertainty          nav_msgs/OccupancyGrid CDR, 100 U / 0.5, unknown -1
  {prefix}/out/{source}/grid/gridmap              grid_map_msgs/GridMap CDR, every layer
  {prefix}/out/{source}/grid/costmap              nav_msgs/OccupancyGrid CDR graded for Nav2 (layers.nav2_costs)
  {prefix}/out/{source}/cell?x=..;y=..            ContextDistribution of the cell (grid frame, metres)
  {prefix}/out/{source}/cell?path=x0,y0;x1,y1;..  PathReply: the known cells along the polyline
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.images import encode_age_png, encode_count_png, encode_maps_png16
from gcdtrav.schemas.messages import ContextDistribution, GridHeader, GridMessage, PathReply, Pose2D
from gcdtrav.schemas.settings import GridCamera, GridSettings, RiskSettings
from gcdtrav.service.grid.fusion import GridSpec, GroundGrid
from gcdtrav.service.grid.geometry import CameraMount, PinholeCamera, depth_points, ground_points, map_cell_pixels
from gcdtrav.service.grid.layers import GridLayers, grid_layers, nav2_costs
from gcdtrav.service.ros.cdr import (
    RosTopic,
    decode_camera_info,
    decode_depth,
    decode_pose,
    occupancy_cdr,
    occupancy_values_cdr,
)
from gcdtrav.service.ros.grid_map import grid_map_cdr
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
GRID_MAP_BASIC_LAYERS = ["traversability"]  # a GridMap cell is valid where T is (grid_map's basic layers)


@dataclass
class CameraState:
    """One camera of a grid: intrinsics (configured or from CameraInfo), mount, latest depth, ROS topic."""

    config: GridCamera
    max_range_m: float
    camera: PinholeCamera | None = None
    depth: NDArray[np.float32] | None = None
    ros: RosTopic | None = None  # the topic of its last frame, if a ROS camera

    def __post_init__(self) -> None:
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

    def base_points(
        self, map_shape: tuple[int, int], image_size: tuple[int, int]
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Ground (or depth) points in the base frame of every map patch, and which patches have one."""
        camera = self.camera_for(image_size)
        u, v = map_cell_pixels(map_shape, image_size)
        if self.depth is not None:
            depth = np.asarray(cv2.resize(self.depth, image_size, interpolation=cv2.INTER_NEAREST), np.float32)
            return depth_points(camera, self.mount, u, v, depth, self.max_range_m)
        key = (map_shape, image_size, camera)
        if key not in self._ground_cache:  # a fixed camera: the same rays every frame
            self._ground_cache = {key: ground_points(camera, self.mount, u, v, self.max_range_m)}
        return self._ground_cache[key]


@dataclass
class SourceGrid:
    """One grid, its cameras and the robot's latest pose; published and queried under ``config.source``."""

    config: GridSettings
    grid: GroundGrid
    pose: Pose2D | None = None
    seq: int = -1
    cameras: dict[str, CameraState] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.lock = threading.Lock()
        self.cameras = {c.source: CameraState(c, self.config.max_range_m) for c in self.config.camera_list()}

    def fuse(
        self,
        camera: CameraState,
        weights: NDArray[np.floating],
        image_size: tuple[int, int],
        stamp: float,
        anchors: AnchorSet,
        match: NDArray[np.floating] | None = None,
    ) -> int:
        points, valid = camera.base_points((weights.shape[1], weights.shape[2]), image_size)
        flat = weights.reshape(weights.shape[0], -1)[:, valid].astype(np.float32)
        scores = None if match is None else np.asarray(match, np.float32).reshape(-1)[valid]
        ground = points[valid]
        if self.pose is not None:  # into the odometry frame, and keep the robot at the grid's centre
            c, s = math.cos(self.pose.yaw), math.sin(self.pose.yaw)
            ground = ground @ np.array([[c, s], [-s, c]]) + np.array([self.pose.x, self.pose.y])
            half = self.grid.spec.cells * self.grid.spec.resolution_m / 2
            self.grid.scroll_to((self.pose.x - half, self.pose.y - half))
        landed = self.grid.add(ground, flat, stamp, anchors, scores)
        self.seq += 1
        return landed

    def ros_topic(self) -> RosTopic | None:
        """The ROS topic the grid's ROS outputs derive from: its first camera (in the configured order) that
        has sent a ROS frame; None if none has."""
        return next((camera.ros for camera in self.cameras.values() if camera.ros is not None), None)


@dataclass(frozen=True)
class GridUpdate:
    """One frame's grid outputs, under the grid's ``source``: the message, and the CDRs that are enabled
    (OccupancyGrids of T and U, the GridMap, the Nav2 costmap); ``ros``: the topic ROS outputs derive from."""

    source: str
    message: GridMessage
    occupancy: bytes | None = None
    uncertainty: bytes | None = None
    grid_map: bytes | None = None
    costmap: bytes | None = None
    ros: RosTopic | None = None


GridInput = tuple[str, str, Callable[[str, bytes], None], str]  # key, grid or camera, setter, rejection reason


class GridOutputs:
    """All configured grids of a service; thread-safe (frames from the worker, queries from zenoh).

    ``sources``: the grids by the source they are published under; frames arrive by camera source.
    """

    def __init__(
        self,
        configs: list[GridSettings],
        anchor_count: int,
        instance: str,
        risk: RiskSettings | None = None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.instance, self.risk, self.clock = instance, risk or RiskSettings(), clock
        self.sources = {c.source: SourceGrid(c, GroundGrid(_spec(c), anchor_count)) for c in configs}
        self.camera_grids = {camera: grid for grid in self.sources.values() for camera in grid.cameras}

    def inputs(self) -> list[GridInput]:
        """What the grids subscribe to besides the maps: pose streams (by grid), CameraInfo and depth (by
        camera), with their setters and the reason a bad message is counted under."""
        found: list[GridInput] = []
        for grid in self.sources.values():
            if grid.config.pose_key is not None:
                found.append((grid.config.pose_key, grid.config.source, self.set_pose, "bad_pose"))
            for camera in grid.cameras.values():
                for key, setter, reason in (
                    (camera.config.camera_info_key, self.set_camera_info, "bad_camera_info"),
                    (camera.config.depth_key, self.set_depth, "bad_depth"),
                ):
                    if key is not None:
                        found.append((key, camera.config.source, setter, reason))
        return found

    def set_pose(self, source: str, payload: bytes) -> None:
        """The pose of the grid published under ``source``."""
        grid = self.sources[source]
        pose = decode_pose(payload, grid.config.pose_format)
        with grid.lock:
            grid.pose = pose

    def pose_of(self, camera: str) -> Pose2D | None:
        """The latest pose of the robot carrying camera ``camera`` (its grid's pose stream); None: unknown."""
        grid = self.camera_grids.get(camera)
        if grid is None:
            return None
        with grid.lock:
            return grid.pose

    def set_camera_info(self, camera: str, payload: bytes) -> None:
        intrinsics = decode_camera_info(payload)
        grid = self.camera_grids[camera]
        with grid.lock:
            grid.cameras[camera].camera = intrinsics

    def set_depth(self, camera: str, payload: bytes) -> None:
        depth = decode_depth(payload)
        grid = self.camera_grids[camera]
        with grid.lock:
            grid.cameras[camera].depth = depth

    def on_frame(
        self,
        source: str,
        record: FrameRecord,
        weights: NDArray[np.floating],
        match: NDArray[np.floating] | None = None,
        ros: RosTopic | None = None,
    ) -> GridUpdate | None:
        """Fuse a processed frame of camera ``source`` (its weights and match scores per map patch, its ROS
        topic if a ROS camera) into its grid; what to publish, or None."""
        grid = self.camera_grids.get(source)
        if grid is None:
            return None
        camera = grid.cameras[source]
        with grid.lock:
            camera.ros = ros or camera.ros
            if camera.camera is None:
                log.warning("grid of %s: no intrinsics yet (waiting for CameraInfo), frame not fused", source)
                return None
            grid.fuse(camera, weights, record.image_size, record.stamp, record.anchors, match)
            anchors = record.anchors
            positions, widths = np.asarray(anchors.positions), np.asarray(anchors.widths)
            risk = self.risk
            layers = grid_layers(grid.grid, positions, widths, risk.alpha, risk.tau, grid.config.lethal_tau)
            header = self.header(grid, anchors.version)
            ros_topic = grid.ros_topic()
        return self.encode_update(grid.config, header, layers, ros_topic)

    def encode_update(
        self, config: GridSettings, header: GridHeader, layers: GridLayers, ros: RosTopic | None
    ) -> GridUpdate:
        """The payloads of one grid update (encoded outside the grid's lock)."""
        maps = (layers.traversability, layers.uncertainty, layers.cvar, layers.p_below, layers.match)
        t, u, cvar, p_below, match = encode_maps_png16(*(np.nan_to_num(values) for values in maps))
        message = GridMessage(
            header=header,
            traversability_png=t,
            uncertainty_png=u,
            count_png=encode_count_png(layers.count),
            cvar_png=cvar,
            p_below_png=p_below,
            match_png=match,
            age_png=encode_age_png(layers.age),
        )
        known = layers.known
        occupancy = uncertainty = grid_map = costmap = None
        if config.occupancy_grid:
            occupancy = occupancy_cdr(header, 1.0 - layers.traversability, known)
            uncertainty = occupancy_cdr(header, layers.uncertainty / 0.5, known)
        if config.grid_map:
            grid_map = grid_map_cdr(header, layers.float_layers(), GRID_MAP_BASIC_LAYERS)
        if config.costmap:
            costs = nav2_costs(layers, config.lethal_probability, config.min_match)
            costmap = occupancy_values_cdr(header, costs)
        return GridUpdate(config.source, message, occupancy, uncertainty, grid_map, costmap, ros)

    def header(self, grid: SourceGrid, version: str) -> GridHeader:
        pose = grid.pose
        stamp = grid.grid.stamp or 0.0
        return GridHeader(
            source=grid.config.source,
            seq=grid.seq,
            stamp=stamp,
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
            alpha=self.risk.alpha,
            tau=self.risk.tau,
            expired_cells=int(grid.grid.expired.sum()),
            age_s=self.clock() - stamp if grid.grid.stamp is not None else None,
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


def _spec(config: GridSettings) -> GridSpec:
    return GridSpec(config.size_m, config.resolution_m, config.half_life_s, config.max_age_s)
