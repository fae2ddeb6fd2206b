"""A grid's geometry from ROS tf: its tf tree, and from it the robot's pose (odom_frame -> base_frame) and each
camera's mount (base_frame -> the camera's frame), handed to the grid as they become known or change.

No middleware: the bus gives each /tf and /tf_static payload to ``on_message``; the grid's outputs tell the
camera frames they learn (``camera_frame``). Which frame a camera is: its configured ``frame_id``, else the
header frame_id of its images, else its CameraInfo's (docs/grid.md, "Mount and pose from tf").
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable

import numpy as np
from gcdtrav.schemas.inputs import RejectedInput
from gcdtrav.schemas.messages import Pose2D
from gcdtrav.schemas.settings import GridCamera, GridTfSettings
from gcdtrav.service.grid.geometry import CameraMount, mount_from_axes
from gcdtrav.service.ros.tf import Transform, decode_tf_message
from gcdtrav.service.ros.tf_tree import TfLookupError, TransformTree

log = logging.getLogger("gcdtrav.service")

AddPose = Callable[[str, Pose2D], None]  # (grid source, pose)
SetMount = Callable[[str, CameraMount, str], None]  # (camera source, mount, origin "tf")
FRAME_SOURCES = ("settings", "image", "camera_info")  # where a camera's frame came from, strongest first
NO_FRAME = "its tf frame is not known: no frame_id set, and no image or CameraInfo with a header frame_id yet"


def is_optical(frame: str, axes: str) -> bool:
    """Whether a camera frame has optical axes (z forward, x right, y down): ROS names such frames
    ``*_optical_frame`` (REP 103); ``frame_axes`` overrides the name."""
    return axes == "optical" or (axes == "auto" and "optical" in frame)


def _stronger(known: str, new: str) -> bool:
    return FRAME_SOURCES.index(known) < FRAME_SOURCES.index(new)


class GridTf:
    """One grid's tf tree; thread-safe (payloads from zenoh's threads, camera frames from the worker).

    ``add_pose`` and ``set_mount`` are called after the tree changed, still under its lock so that two messages'
    mounts arrive in the order they were computed (the lock order is this lock, then the grid's or the pose
    buffer's; nothing holding those calls in here): a pose at each newer stamp the chain odom_frame -> base_frame
    reaches, a mount whenever a camera's transform is first known or changes.
    ``waiting`` says, per pose or camera, why tf does not give it yet (a lookup error), for status and logs.
    """

    def __init__(
        self, grid: str, config: GridTfSettings, cameras: list[GridCamera], add_pose: AddPose, set_mount: SetMount
    ) -> None:
        self.grid, self.config = grid, config
        self.add_pose, self.set_mount = add_pose, set_mount
        self.tree = TransformTree(config.buffer_s)
        self.lock = threading.Lock()
        self.axes = {camera.source: camera.frame_axes for camera in cameras} if config.mount else {}
        # camera -> (frame, where it came from); a frame from a stronger source is never replaced by a weaker one
        self.frames: dict[str, tuple[str, str]] = {
            camera.source: (camera.frame_id, "settings") for camera in cameras if config.mount and camera.frame_id
        }
        self.mounts: dict[str, Transform] = {}  # the transform each camera's mount was last set from
        self.pose_stamp = -math.inf  # the newest pose handed over
        self.waiting: dict[str, str] = {"pose": "no tf yet"} if config.pose else {}
        self.waiting |= {camera: NO_FRAME for camera in self.axes if camera not in self.frames}
        self.waiting |= {camera: "no tf yet" for camera in self.frames}

    def on_message(self, payload: bytes, static: bool) -> list[RejectedInput]:
        """A /tf (or /tf_static) TFMessage: its transforms into the tree, then the pose and mounts it changes.
        Returns the transforms refused (each counted by the caller); RejectedInput bad_tf if it does not decode."""
        kept, refused = decode_tf_message(payload)
        with self.lock:
            for item in kept:
                try:
                    self.tree.add(item, static)
                except RejectedInput as err:
                    refused.append(err)
            pose = self._pose() if self.config.pose else None
            self._hand_over(pose, self._mounts() if kept else [])
        return refused

    def camera_frame(self, camera: str, frame_id: str, origin: str) -> None:
        """The frame id ``camera``'s images (origin "image") or CameraInfo (origin "camera_info") carry."""
        frame_id = frame_id.lstrip("/")
        if camera not in self.axes or not frame_id:
            return
        with self.lock:
            known = self.frames.get(camera)
            if known is not None and (known[0] == frame_id or _stronger(known[1], origin)):
                return
            if known is not None and known[1] == origin:
                log.warning("grid %s: camera %s's frame changed from %s to %s", self.grid, camera, known[0], frame_id)
            self.frames[camera] = (frame_id, origin)
            self._hand_over(None, self._mounts())

    # ---- under the lock ------------------------------------------------------------------------------
    def _pose(self) -> Pose2D | None:
        """The pose at the newest stamp the whole chain odom_frame -> base_frame knows, if newer than the last."""
        odom, base = self.config.odom_frame, self.config.base_frame
        try:
            stamp = self.tree.latest_common_time(odom, base)
            if stamp is None:  # only static links: no timeline to place frames on
                raise TfLookupError("tf_static_pose", f"'{odom}' -> '{base}' is static: the pose needs /tf")
            if stamp <= self.pose_stamp:
                return None
            transform = self.tree.lookup(odom, base, stamp)
        except TfLookupError as err:
            self._wait("pose", err)
            return None
        self.waiting.pop("pose", None)
        self.pose_stamp = stamp
        x, y, _ = transform.translation
        try:
            return Pose2D.validated({"stamp": stamp, "frame_id": odom, "x": x, "y": y, "yaw": transform.yaw()})
        except ValueError as err:  # a position beyond reach: the pose is not used
            self.waiting["pose"] = f"tf_bad_pose: {err}"
            return None

    def _mounts(self) -> list[tuple[str, CameraMount]]:
        """Every camera whose base_frame -> camera frame transform became known or changed."""
        changed = []
        for camera, (frame, _) in self.frames.items():
            try:
                transform = self.tree.lookup(self.config.base_frame, frame)
            except TfLookupError as err:
                self._wait(camera, err)
                continue
            self.waiting.pop(camera, None)
            if self.mounts.get(camera) == transform:
                continue
            self.mounts[camera] = transform
            optical = is_optical(frame, self.axes[camera])
            changed.append((camera, mount_from_axes(np.array(transform.translation), transform.matrix(), optical)))
        return changed

    def _wait(self, what: str, err: TfLookupError) -> None:
        if self.waiting.get(what) != str(err):
            thing = "pose" if what == "pose" else f"mount of {what}"
            log.info("grid %s: tf does not give the %s yet: %s", self.grid, thing, err)
        self.waiting[what] = str(err)

    def _hand_over(self, pose: Pose2D | None, mounts: list[tuple[str, CameraMount]]) -> None:
        if pose is not None:
            self.add_pose(self.grid, pose)
        for camera, mount in mounts:
            log.info("grid %s: camera %s's mount from tf: %s", self.grid, camera, mount)
            self.set_mount(camera, mount, "tf")
