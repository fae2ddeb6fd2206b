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
import time
from collections.abc import Callable

import numpy as np
from gcdtrav.schemas.messages import ContextDistribution, GridHeader, PathReply, Pose2D
from gcdtrav.schemas.settings import GridSettings, RiskSettings
from gcdtrav.service.grid.fusion import GroundGrid
from gcdtrav.service.grid.layers import grid_layers
from gcdtrav.service.ros.cdr import (
    RosTopic,
    decode_camera_info,
    decode_depth,
    decode_pose,
)
from gcdtrav.service.runtime.grids import answers
from gcdtrav.service.runtime.grids.encoding import FusedGrid, GridUpdate, grid_header
from gcdtrav.service.runtime.grids.state import CameraState, SourceGrid, grid_spec
from gcdtrav.service.runtime.history import FrameRecord
from numpy.typing import NDArray

log = logging.getLogger("gcdtrav.service")

GridInput = tuple[str, str, Callable[[str, bytes], None], str]  # key, grid or camera, setter, rejection reason
# Called under the grid's lock after each fusion: the grid, the camera that fed it, the frame's image if known.
AfterFusion = Callable[[SourceGrid, CameraState, NDArray[np.uint8] | None], None]


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
        self.sources = {c.source: SourceGrid(c, GroundGrid(grid_spec(c), anchor_count)) for c in configs}
        self.camera_grids = {camera: grid for grid in self.sources.values() for camera in grid.cameras}
        self.after_fusion: AfterFusion | None = None  # the experience's snapshots and questions (service/bus)

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
        image: NDArray[np.uint8] | None = None,
    ) -> GridUpdate | None:
        """``fuse``, then encode: for tools and tests (the service fuses in the worker, encodes in the outputs)."""
        fused = self.fuse(source, record, weights, match, ros, image)
        return fused.encode() if fused is not None else None

    def fuse(
        self,
        source: str,
        record: FrameRecord,
        weights: NDArray[np.floating],
        match: NDArray[np.floating] | None = None,
        ros: RosTopic | None = None,
        image: NDArray[np.uint8] | None = None,
    ) -> FusedGrid | None:
        """Fuse a processed frame of camera ``source`` (its weights and match scores per map patch, its ROS
        topic if a ROS camera, its image for ``after_fusion``) into its grid; the grid's layers to publish, or
        None (not a grid's camera, or no intrinsics yet)."""
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
            if self.after_fusion is not None:
                self.after_fusion(grid, camera, image)
            anchors = record.anchors
            positions, widths = np.asarray(anchors.positions), np.asarray(anchors.widths)
            risk = self.risk
            layers = grid_layers(grid.grid, positions, widths, risk.alpha, risk.tau, grid.config.lethal_tau)
            header = self.header(grid, anchors.version)
            ros_topic = grid.ros_topic()
        return FusedGrid(grid.config, header, layers, ros_topic)

    def header(self, grid: SourceGrid, version: str) -> GridHeader:
        return grid_header(grid, version, self.instance, self.risk, self.clock)

    def answer(
        self, source: str, raw_parameters: str, risk: RiskSettings | None = None
    ) -> ContextDistribution | PathReply:
        """A cell's or a path's distributions, over the anchor set the grid's weights were fused with."""
        return answers.answer(self.sources, source, raw_parameters, risk)
