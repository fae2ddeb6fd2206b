"""Where the viewer draws a camera whose grid takes its mount from tf (issue 40's gap): where the grid's status
says the grid fuses it, never the settings' mount: nothing before tf gives it, then tf's mount; and the pose
the last frame was fused at beside the robot."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("foxglove", reason="the view extra: pip install 'gcdtrav[view]'")
pytest.importorskip("google.protobuf")
pytest.importorskip("matplotlib")

from gcdtrav.client.view.viewer import Viewer, ViewOptions
from gcdtrav.schemas.messages import CameraPlacement, GridCameraStatus, GridMessage, GridStatus
from protobuf_decode import decode_foxglove
from test_view_layers import rotate
from view_fakes import FakeClient, grid_payload, maps_payload
from zenoh_helpers import wait_until

SETTINGS = """
grids:
  - source: cam
    intrinsics: {fx: 100, fy: 100, cx: 80, cy: 60, width: 160, height: 120}
    mount: {z: 1.0}
    tf: {mount: true, pose: true}
"""
MOUNT_FIELDS = {"x": 0.3, "y": 0.05, "z": 0.9, "roll": 0.0, "pitch": 0.35, "yaw": 0.1}
TF_MOUNT = CameraPlacement(**MOUNT_FIELDS)  # what tf gave the grid


@dataclass
class PlacingClient(FakeClient):
    """The stand-in service, whose grid 'cam' reports its camera's mount as ``camera`` says."""

    camera: GridCameraStatus = field(default_factory=lambda: GridCameraStatus(mount=None))

    def statuses(self, timeout: float = 5.0) -> list[Any]:
        grid = GridStatus(source="cam", frame_id="odom", cameras={"cam": self.camera})
        return [status.model_copy(update={"grids": [grid]}) for status in super().statuses(timeout)]


@pytest.fixture()
def viewer(tmp_path: Path) -> Iterator[tuple[Viewer, PlacingClient, list[tuple[str, dict[str, Any]]]]]:
    settings = tmp_path / "gcdtrav.yaml"
    settings.write_text(SETTINGS)
    client = PlacingClient()
    viewer = Viewer(client, ViewOptions(port=0, status_period_s=0.1, settings=settings))  # type: ignore[arg-type]
    emitted: list[tuple[str, dict[str, Any]]] = []
    emit = viewer.emit

    def recording(channel: Any, message: Any, log_time: int | None = None) -> None:
        if hasattr(message, "get_schema"):
            emitted.append((channel.topic(), decode_foxglove(message)))
        emit(channel, message, log_time)

    viewer.emit = recording  # type: ignore[method-assign]
    viewer.start()
    try:
        yield viewer, client, emitted
    finally:
        viewer.close()


def camera_mounts(emitted: list[tuple[str, dict[str, Any]]]) -> list[dict[str, Any]]:
    return [
        transform
        for topic, message in emitted
        if topic == "/gcdtrav/cam/tf"
        for transform in message["transforms"]
        if transform["child_frame_id"] == "front"
    ]


def show_maps(viewer: Viewer, client: PlacingClient) -> None:
    before = viewer.shown["maps"]
    client.session.put("gcdtrav/out/cam/maps", maps_payload("cam", (4, 4), (160, 120), seq=before))
    assert wait_until(lambda: viewer.shown["maps"] > before, 30)


def test_a_tf_mounted_camera_is_drawn_where_tf_puts_it_never_at_the_settings_mount(viewer: Any) -> None:
    view, client, emitted = viewer
    assert wait_until(lambda: "cam" in view.grid_cameras, 30)  # the status says: no mount yet
    show_maps(view, client)
    scene = [entity for topic, m in emitted if topic == "/gcdtrav/cam/robot" for entity in m["entities"]]
    assert camera_mounts(emitted) == [] and scene == []  # not drawn at the settings' z = 1.0 while tf lacks it

    client.camera = GridCameraStatus(mount="tf", placement=TF_MOUNT)  # tf gave the grid its mount
    assert wait_until(lambda: view.grid_cameras["cam"].placement is not None, 30)
    show_maps(view, client)
    (transform,) = camera_mounts(emitted)
    t = transform["translation"]
    assert (t["x"], t["y"], t["z"]) == pytest.approx((0.3, 0.05, 0.9))
    from gcdtrav.service.grid.geometry import CameraMount

    optical = CameraMount(**MOUNT_FIELDS).rotation_optical
    for axis in np.eye(3):  # the optical axes where the service's projection has them
        assert np.allclose(rotate(transform["rotation"], axis), optical @ axis, atol=1e-9)
    entities = [e for topic, m in emitted if topic == "/gcdtrav/cam/robot" for e in m["entities"]]
    assert {e["id"] for e in entities} == {"cam/frustum", "cam/robot"}


def test_the_grid_shows_the_pose_its_last_frame_was_fused_at(viewer: Any) -> None:
    view, client, emitted = viewer
    message = GridMessage.unpack(grid_payload("cam", robot=(2.0, 1.0, 0.0)))
    header = message.header.model_copy(update={"capture_pose": (1.2, 1.0, 0.1)})
    client.session.put("gcdtrav/out/cam/grid", message.model_copy(update={"header": header}).pack())
    assert wait_until(lambda: view.shown["grid"] == 1, 30)
    entities = {e["id"]: e for topic, m in emitted if topic == "/gcdtrav/cam/robot" for e in m["entities"]}
    capture = entities["cam/capture"]
    assert capture["frame_id"] == "odom"  # in the grid frame, where the robot was at the frame's capture
    position = capture["arrows"][0]["pose"]["position"]
    assert (position["x"], position["y"]) == pytest.approx((1.2, 1.0))
    assert {"cam/robot", "cam/capture"} <= set(entities)  # the robot's marker stays (no frustum known)


def test_which_mount_is_drawn() -> None:
    """The grid's reported mount first; the settings' only for a grid that does not take it from tf, and only
    while the status has no mount values (none yet, or a service before 1.4)."""
    from gcdtrav.client.view.frames import CameraSetup, camera_mount
    from gcdtrav.schemas.settings import CameraMountSettings

    typed = CameraSetup("cam", CameraMountSettings(z=1.5), None)
    from_tf = CameraSetup("cam", CameraMountSettings(z=1.5), None, mount_from_tf=True)
    placed = GridCameraStatus(mount="tf", placement=TF_MOUNT)
    assert camera_mount(typed, None) == CameraMountSettings(z=1.5)
    assert camera_mount(typed, GridCameraStatus(mount="settings")) == CameraMountSettings(z=1.5)  # a 1.3 service
    assert camera_mount(from_tf, None) is None and camera_mount(from_tf, GridCameraStatus(mount=None)) is None
    assert camera_mount(typed, GridCameraStatus(mount="tf")) is None  # tf's mount without its values: unknown
    assert camera_mount(from_tf, placed) == CameraMountSettings(**MOUNT_FIELDS)
    assert camera_mount(None, placed) == CameraMountSettings(**MOUNT_FIELDS)  # no settings file: still placed
    assert camera_mount(None, None) is None
