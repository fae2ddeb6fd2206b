"""A grid update's payloads: the GridMessage (16-bit PNG layers) and the enabled ROS CDRs."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from gcdtrav.schemas.experience import OperatorQuestion
from gcdtrav.schemas.grid_layers import encode_layers
from gcdtrav.schemas.messages import GridHeader, GridMessage
from gcdtrav.schemas.ros_nav import speed_mask_values
from gcdtrav.schemas.settings import GridSettings, RiskSettings
from gcdtrav.service.grid import speed
from gcdtrav.service.grid.layers import GridLayers, nav2_costs
from gcdtrav.service.ros.cdr import RosTopic, nav2_costmap_cdr, occupancy_cdr, occupancy_values_cdr, speed_limit_cdr
from gcdtrav.service.ros.grid_map import grid_map_cdr
from gcdtrav.service.runtime.grids.state import SourceGrid
from numpy.typing import NDArray

GRID_MAP_BASIC_LAYERS = ["traversability"]  # a GridMap cell is valid where T is (grid_map's basic layers)


@dataclass(frozen=True)
class SpeedUpdate:
    """A grid's speed filter outputs (docs/grid.md, "Speed from uncertainty"): the mask, a nav_msgs/OccupancyGrid
    of percent of maximum speed (None: not due yet, ``speed.rate_hz`` bounds it), and the nav2_msgs/SpeedLimit
    at the robot's pose; ``safe``: both the floor everywhere (a stale grid, a stopping service)."""

    source: str
    mask: bytes | None
    limit: bytes
    frame_id: str  # the grid's frame, the mask's and the filter info's
    ros: RosTopic | None
    safe: bool = False


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
    speed: SpeedUpdate | None = None
    nav2_costmap: bytes | None = None  # the costmap as a nav2_msgs/Costmap (the collision monitor's source)


@dataclass(frozen=True)
class FusedGrid:
    """A grid right after a frame was fused into it (``GridOutputs.fuse``, in the worker): its layers and
    header, taken under the grid's lock, for the outputs to encode (``encode``) outside it; the question the
    fusion made the experience ask an operator, if any, to publish beside it."""

    config: GridSettings
    header: GridHeader
    layers: GridLayers
    ros: RosTopic | None  # the topic its ROS outputs derive from
    question: OperatorQuestion | None = None
    speed_mask_due: bool = False  # a grid with speed: this update carries the mask (at most speed.rate_hz)

    def encode(self) -> GridUpdate:
        return encode_update(self.config, self.header, self.layers, self.ros, self.speed_mask_due)


def encode_update(
    config: GridSettings, header: GridHeader, layers: GridLayers, ros: RosTopic | None, speed_mask_due: bool = False
) -> GridUpdate:
    """The payloads of one grid update (encoded outside the grid's lock)."""
    message = GridMessage.model_validate({"header": header, **encode_layers(layers.values())})
    known = layers.known
    occupancy = uncertainty = grid_map = costmap = nav2_costmap = None
    if config.occupancy_grid:
        occupancy = occupancy_cdr(header, 1.0 - layers.traversability, known)
        uncertainty = occupancy_cdr(header, layers.uncertainty / 0.5, known)
    if config.grid_map:
        grid_map = grid_map_cdr(header, layers.float_layers(), GRID_MAP_BASIC_LAYERS)
    if config.costmap:
        costs = nav2_costs(layers, config.lethal_probability, config.min_match)
        costmap = occupancy_values_cdr(header, costs)
        nav2_costmap = nav2_costmap_cdr(header, costs)
    speed_update = None
    if config.speed is not None and layers.speed is not None:
        speed_update = speed_of(config, header, layers.speed, ros, speed_mask_due)
    return GridUpdate(
        config.source, message, occupancy, uncertainty, grid_map, costmap, ros, speed_update, nav2_costmap
    )


def speed_of(
    config: GridSettings,
    header: GridHeader,
    fractions: NDArray[np.float32],
    ros: RosTopic | None,
    with_mask: bool,
    safe: bool = False,
) -> SpeedUpdate:
    """The speed filter's payloads of a grid's speed layer: the limit at the robot's pose (header.robot; the
    floor if it is off the grid or unknown) and, ``with_mask``, the mask."""
    assert config.speed is not None
    robot = header.robot  # None before the grid knows the robot's pose: the limit is then the floor's
    at = None if robot is None else speed.fraction_at(fractions, header.origin, header.resolution, robot[0], robot[1])
    fraction = speed.safe_fraction(config.speed) if at is None else at
    limit = speed_limit_cdr(header.stamp, header.frame_id, speed.limit_percent(fraction))
    mask = occupancy_values_cdr(header, speed_mask_values(fractions)) if with_mask else None
    return SpeedUpdate(config.source, mask, limit, header.frame_id, ros, safe)


def safe_speed(config: GridSettings, header: GridHeader, ros: RosTopic | None) -> SpeedUpdate:
    """The safe mask and limit: the floor everywhere on the grid (docs/grid.md, "Speed from uncertainty")."""
    assert config.speed is not None
    fractions = np.full((header.cells, header.cells), speed.safe_fraction(config.speed), np.float32)
    return speed_of(config, header, fractions, ros, with_mask=True, safe=True)


def grid_header(
    grid: SourceGrid, version: str, instance: str, risk: RiskSettings, clock: Callable[[], float]
) -> GridHeader:
    """The header of a grid's message (and its ROS messages), as of now."""
    pose = grid.pose
    at = grid.fused_at.pose if grid.fused_at is not None else None
    stamp = grid.grid.stamp or 0.0
    return GridHeader(
        source=grid.config.source,
        seq=grid.seq,
        stamp=stamp,
        frame_id=grid.frame_id(),
        origin=grid.grid.origin,
        resolution=grid.grid.spec.resolution_m,
        cells=grid.grid.spec.cells,
        robot=(pose.x, pose.y, pose.yaw) if pose is not None else (0.0, 0.0, 0.0),
        anchor_set_version=version,
        resets=grid.grid.resets,
        last_reset=grid.grid.last_reset,
        known_cells=int(grid.grid.known.sum()),
        instance=instance,
        alpha=risk.alpha,
        tau=risk.tau,
        expired_cells=int(grid.grid.expired.sum()),
        age_s=clock() - stamp if grid.grid.stamp is not None else None,
        capture_stamp=grid.fused_stamp,
        capture_pose=(at.x, at.y, at.yaw) if at is not None else None,
    )
