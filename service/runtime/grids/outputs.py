"""Ground grids on the bus: per configured grid, project each frame of its cameras onto the ground, fuse
them, publish the grid and its layers, and answer cell and path queries in metres.

Keys, for a grid published under {source} (its single camera's source, or its name; docs/grid.md):
  {prefix}/out/{source}/grid                      GridMessage (msgpack): T, U, counts, CVaR, p_below, match, age
  {prefix}/out/{source}/grid/occupancy            nav_msgs/OccupancyGrid CDR, cost = 100 (1 - T), unknown -1
  {prefix}/out/{source}/grid/uncertainty          nav_msgs/OccupancyGrid CDR, 100 U / 0.5, unknown -1
  {prefix}/out/{source}/grid/gridmap              grid_map_msgs/GridMap CDR, every layer
  {prefix}/out/{source}/grid/costmap              nav_msgs/OccupancyGrid CDR graded for Nav2 (layers.nav2_costs)
  {prefix}/out/{source}/grid/speed_mask           nav_msgs/OccupancyGrid CDR, Nav2 speed filter mask (grid/speed.py)
  {prefix}/out/{source}/grid/speed_limit          nav2_msgs/SpeedLimit CDR at the robot's pose
  {prefix}/out/{source}/cell?x=..;y=..            ContextDistribution of the cell (grid frame, metres)
  {prefix}/out/{source}/cell?path=x0,y0;x1,y1;..  PathReply: the known cells along the polyline
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from functools import partial

import numpy as np
from gcdtrav.schemas.experience import OperatorQuestion
from gcdtrav.schemas.inputs import RejectedInput
from gcdtrav.schemas.messages import ContextDistribution, GridHeader, GridStatus, PathReply, Pose2D
from gcdtrav.schemas.settings import GridSettings, RiskSettings
from gcdtrav.service.grid.fusion import GroundGrid
from gcdtrav.service.grid.geometry import CameraMount
from gcdtrav.service.grid.layers import grid_layers
from gcdtrav.service.grid.poses import PoseAt
from gcdtrav.service.grid.speed import speed_fractions
from gcdtrav.service.ros.cdr import RosTopic, decode_camera_info_frame, decode_depth, decode_pose
from gcdtrav.service.runtime.grids import answers
from gcdtrav.service.runtime.grids.encoding import FusedGrid, SpeedUpdate, grid_header, safe_speed
from gcdtrav.service.runtime.grids.health import NO_INTRINSICS, NO_MOUNT
from gcdtrav.service.runtime.grids.state import CameraState, SourceGrid, grid_spec, grid_status
from gcdtrav.service.runtime.grids.tf import GridTf
from gcdtrav.service.runtime.history import FrameRecord
from numpy.typing import NDArray

log = logging.getLogger("gcdtrav.service")

GridInput = tuple[str, str, Callable[[str, bytes], None], str]  # key, grid or camera, setter, rejection reason
# key, grid, static (/tf_static: transient local), handler: a TFMessage's payload -> the transforms it refused
TfInput = tuple[str, str, bool, Callable[[bytes], list[RejectedInput]]]
# Called under the grid's lock after each fusion with the grid, the camera that fed it and the frame's image if
# known: the experience's snapshot and question, in memory only (no I/O under the lock). The question it returns
# leaves with the frame's grid (``FusedGrid.question``), put by the bus like every other payload.
AfterFusion = Callable[[SourceGrid, CameraState, NDArray[np.uint8] | None], OperatorQuestion | None]


@dataclass(frozen=True)
class CapturePose:
    """Where the robot was when a frame was taken: the capture stamp on the pose stream's clock, and the
    pose there or why there is none."""

    stamp: float
    at: PoseAt


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
        clock_mode: str = "estimated",
        after_fusion: AfterFusion | None = None,
    ) -> None:
        """``clock_mode``: the service's ``clock`` setting ("estimated" or "synced"), how an unstamped frame's
        receipt becomes a stamp on the pose stream's clock (``_capture_stamp``). ``after_fusion``: the
        experience's (``Experience.after_fusion``), or None."""
        self.instance, self.risk, self.clock, self.clock_mode = instance, risk or RiskSettings(), clock, clock_mode
        self.sources = {c.source: SourceGrid(c, GroundGrid(grid_spec(c), anchor_count)) for c in configs}
        self.camera_grids = {camera: grid for grid in self.sources.values() for camera in grid.cameras}
        self._after_fusion = after_fusion
        # grids whose mounts or pose come from tf: their trees hand over poses and mounts as they learn them
        self.tf = {
            c.source: GridTf(c.source, c.tf, c.camera_list(), self.add_pose, self.set_mount)
            for c in configs
            if c.tf is not None
        }
        for source, tf in self.tf.items():
            self.sources[source].tf_waiting = tf.waiting

    def tf_inputs(self) -> list[TfInput]:
        """The /tf and /tf_static subscriptions of the grids that take geometry from tf."""
        found: list[TfInput] = []
        for source, tf in self.tf.items():
            found.append((tf.config.tf_static_key, source, True, partial(tf.on_message, static=True)))
            found.append((tf.config.tf_key, source, False, partial(tf.on_message, static=False)))
        return found

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
        """A pose of the grid published under ``source`` (its pose stream's payload); MessageError if bad."""
        self.add_pose(source, decode_pose(payload, self.sources[source].config.pose_format))

    def add_pose(self, grid_source: str, pose: Pose2D) -> None:
        """A decoded pose of the grid published under ``grid_source`` (its pose stream, or tf): into its buffer,
        waking a frame waiting for it. Takes only the buffer's lock, never the grid's."""
        grid = self.sources[grid_source]
        now = self.clock()
        grid.poses.add(pose, now)
        grid.health.pose_received_at = now

    def pose_at(self, camera: str, stamp: float | None, received_at: float, wait: bool = False) -> CapturePose | None:
        """The one lookup of where the robot carrying ``camera`` was when its frame was taken: fusion's (``wait``:
        up to ``poses.wait_s`` for a lagging stream) and reuse's (``reuse_pose``: never waits). ``stamp``: the
        frame's capture stamp, None for a bare image, then taken at its receipt ``received_at`` (the service's
        clock; see ``_capture_stamp``). None: not a grid's camera."""
        grid = self.camera_grids.get(camera)
        if grid is None:
            return None
        capture = self._capture_stamp(grid, stamp, received_at)
        if not grid.expects_pose():  # no pose stream: the grid is in base_link
            return CapturePose(capture, PoseAt(None))
        # Waited for outside the grid's lock, only by a frame that can be fused (intrinsics known).
        wait_s = self._pose_wait_s(grid) if wait and grid.cameras[camera].camera is not None else 0.0
        return CapturePose(capture, grid.poses.wait(capture, wait_s))

    def reuse_pose(self, camera: str, stamp: float | None, received_at: float) -> Pose2D | None:
        """The pose the reuse compares a frame's view by (service/runtime/triage/reuse.py): its capture pose
        (``pose_at``, not waited for: the triage must not stall), else the newest pose (docs/grid.md, *Which
        pose*): a missing pose must not blind the reuse to the robot's motion, and a pose of another time can
        only make it infer a frame it might have reused. Fusion never falls back: its cells would land where
        the robot was not. None: not a grid's camera, or no pose at all."""
        capture = self.pose_at(camera, stamp, received_at)
        if capture is None:
            return None
        return capture.at.pose or self.camera_grids[camera].pose

    def set_mount(self, camera_source: str, mount: CameraMount, origin: str) -> None:
        """Camera ``camera_source``'s mount in the base frame, from ``origin`` ("settings" or "tf"); the next
        frame's ground rays are computed afresh."""
        grid = self.camera_grids[camera_source]
        with grid.lock:
            grid.cameras[camera_source].set_mount(mount, origin)

    def set_camera_info(self, camera: str, payload: bytes) -> None:
        intrinsics, frame_id = decode_camera_info_frame(payload)
        grid = self.camera_grids[camera]
        with grid.lock:
            state = grid.cameras[camera]
            state.camera, state.intrinsics_origin = intrinsics, "camera_info"
        self._camera_frame(grid, camera, frame_id, "camera_info")

    def _camera_frame(self, grid: SourceGrid, camera: str, frame_id: str, origin: str) -> None:
        """A frame id the camera's images or CameraInfo carry: its tf frame, for a grid with tf.mount. Outside the
        grid's lock: a mount it makes known is set under it."""
        tf = self.tf.get(grid.config.source)
        if tf is not None:
            tf.camera_frame(camera, frame_id, origin)

    def set_depth(self, camera: str, payload: bytes) -> None:
        depth = decode_depth(payload)
        grid = self.camera_grids[camera]
        with grid.lock:
            grid.cameras[camera].depth = depth

    def fuse(
        self,
        source: str,
        record: FrameRecord,
        weights: NDArray[np.floating],
        match: NDArray[np.floating] | None = None,
        ros: RosTopic | None = None,
        image: NDArray[np.uint8] | None = None,
        unstamped: bool = False,
    ) -> FusedGrid | None:
        """Fuse a processed frame of camera ``source`` (its weights and match scores per map patch, its ROS
        topic if a ROS camera, its image for ``after_fusion``) into its grid, projected from the robot's pose at
        the frame's capture stamp (``unstamped``: a bare image, stamped with its receipt; see
        ``pose_at``); the grid's layers to publish, or None (not a grid's camera, or not fused: counted
        by reason in the grid's health)."""
        grid = self.camera_grids.get(source)
        if grid is None:
            return None
        camera = grid.cameras[source]
        self._camera_frame(grid, source, record.frame_id, "image")
        # The pose at capture, waited for (bounded) outside the grid's lock: the pose stream may lag the frame.
        capture = self.pose_at(source, None if unstamped else record.stamp, record.stamp, wait=True)
        assert capture is not None  # a grid's camera
        stamp, at = capture.stamp, capture.at
        with grid.lock:
            camera.ros = ros or camera.ros
            reason = NO_INTRINSICS if camera.camera is None else NO_MOUNT if camera.mount_origin is None else at.reason
            if reason is not None:
                self._not_fused(grid, source, stamp, reason)
                return None
            grid.fuse(camera, weights, record.image_size, record.stamp, record.anchors, match, at.pose)
            grid.fused_at, grid.fused_stamp = at, stamp
            grid.health.fused_frame(source, stamp, self.clock(), grid.config.costmap)
            question = self._after_fusion(grid, camera, image) if self._after_fusion is not None else None
            anchors = record.anchors
            positions, widths = np.asarray(anchors.positions), np.asarray(anchors.widths)
            risk = self.risk
            layers = grid_layers(grid.grid, positions, widths, risk.alpha, risk.tau, grid.config.lethal_tau)
            if grid.config.speed is not None:
                layers = replace(layers, speed=speed_fractions(layers, grid.config.speed, grid.config.resolution_m))
            header = self.header(grid, anchors.version)
            ros_topic = grid.ros_topic()
            mask_due = grid.speed_mask_due(self.clock())
        return FusedGrid(grid.config, header, layers, ros_topic, question, mask_due)

    def unchanged(self, camera: str) -> None:
        """Camera ``camera``'s view was found unchanged and its last maps reused (the triage): its grid's
        evidence still holds, so its speed mask is not stale. Without the grid's lock (one assignment)."""
        grid = self.camera_grids.get(camera)
        if grid is not None:
            grid.health.unchanged_at = self.clock()

    def safe_speed(self, stale_only: bool) -> list[SpeedUpdate]:
        """The safe speed mask and limit (the floor everywhere) of every grid whose live mask must go: it is
        stale (no frame fused for speed.stale_s), or, ``stale_only`` False, the service stops. A grid that never
        handed out a mask, or whose last is already safe, has none to replace."""
        found = []
        for grid in self.sources.values():
            with grid.lock:
                now = self.clock()
                live = grid.speed_mask_at is not None and not grid.speed_safe
                if not (grid.speed_stale(now) if stale_only else live):
                    continue
                if stale_only:
                    log.warning(
                        "grid %s: no frame fused or found unchanged for %.1f s: the safe speed mask (the floor) "
                        "replaces the last",
                        grid.config.source,
                        grid.config.speed.stale_s if grid.config.speed is not None else 0.0,
                    )
                grid.speed_mask_at, grid.speed_safe = now, True
                header, ros_topic = self.header(grid, ""), grid.ros_topic()
            found.append(safe_speed(grid.config, header, ros_topic))
        return found

    def _pose_wait_s(self, grid: SourceGrid) -> float:
        """How long a frame may wait for its pose: ``poses.wait_s`` while the stream is alive (a pose within
        ``max_gap_s``); a stream that stopped would only stall the worker, every frame."""
        heard = grid.health.pose_received_at
        alive = heard is not None and self.clock() - heard <= grid.config.poses.max_gap_s
        return grid.config.poses.wait_s if alive else 0.0

    def _capture_stamp(self, grid: SourceGrid, stamp: float | None, received_at: float) -> float:
        """When the frame was taken on the pose stream's clock. A stamped frame: its stamp (the robot's clock,
        as the poses'). A bare image (``stamp`` None) carries only its receipt on the service's clock: with
        ``clock: synced`` that is the robot's; with ``estimated``, the receipt less the pose stream's learnt
        offset (service minus robot plus the pose link's smallest delay), as a source's clock is learnt."""
        offset = grid.poses.offset_s if stamp is None and self.clock_mode != "synced" else None
        return (received_at if stamp is None else stamp) - (offset or 0.0)

    def _not_fused(self, grid: SourceGrid, camera: str, stamp: float, reason: str) -> None:
        """Count a frame the grid could not fuse; logged once per camera and reason in a row."""
        if grid.health.not_fused_frame(camera, reason, self.clock()):
            log.warning("grid %s: frame of %s (stamp %.3f) not fused: %s", grid.config.source, camera, stamp, reason)

    def statuses(self, clock_offsets: Mapping[str, float]) -> list[GridStatus]:
        """Every grid's health now (``clock_offsets``: each source's learnt clock, for the pose stream's)."""
        found = []
        for grid in self.sources.values():
            with grid.lock:
                found.append(grid_status(grid, self.clock(), clock_offsets))
        return found

    def header(self, grid: SourceGrid, version: str) -> GridHeader:
        return grid_header(grid, version, self.instance, self.risk, self.clock)

    def answer(
        self, source: str, raw_parameters: str, risk: RiskSettings | None = None
    ) -> ContextDistribution | PathReply:
        """A cell's or a path's distributions, over the anchor set the grid's weights were fused with."""
        return answers.answer(self.sources, source, raw_parameters, risk)
