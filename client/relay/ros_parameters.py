"""The ROS 2 node's names and parameters, without rclpy (client/relay/ros2_node.py runs the node): which ROS
parameters it reads, how they become relay settings, where a camera's CameraInfo is."""

from __future__ import annotations

from typing import Any

PARAMETERS = (
    "settings",
    "camera",
    "source",
    "camera_info_key",
    "prefix",
    "input_prefix",
    "jpeg_quality",
    "max_side",
    "credit_timeout_s",
    "stale_after_s",
    "odometry_topic",
    "odometry_key",
    "connect",
    "frames",
    "safe_after_s",
    "safe_floor",
    "max_speed_m_s",
    "outcomes",
    "cmd_vel_topic",
    "cmd_vel_stamped",
    "contact_topic",
    "planned_path_topic",
)
SAFE_MASK_PARAMETERS = {"safe_after_s": "after_s", "safe_floor": "floor", "max_speed_m_s": "max_speed_m_s"}
OUTCOME_PARAMETERS = {
    "cmd_vel_topic": "cmd_vel",
    "cmd_vel_stamped": "cmd_vel_stamped",
    "contact_topic": "contact",
    "planned_path_topic": "planned_path",
}


def camera_info_topic(image_topic: str) -> str:
    """image_transport's convention: the CameraInfo beside the image (a transport's subtopic left out)."""
    parts = image_topic.rstrip("/").split("/")
    if len(parts) > 2 and parts[-1] in ("compressed", "compressedDepth", "theora", "zstd"):
        parts = parts[:-1]
    return "/".join([*parts[:-1], "camera_info"])


def as_list(value: Any) -> list[Any]:
    return list(value) if isinstance(value, list) else [value]


def settings_overrides(parameters: dict[str, Any]) -> dict[str, object]:
    """Relay settings from ROS parameters (on top of the YAML file and the flags)."""
    overrides: dict[str, object] = {
        name: parameters[name]
        for name in ("prefix", "input_prefix", "jpeg_quality", "max_side", "credit_timeout_s", "stale_after_s")
        if name in parameters
    }
    if "camera" in parameters or "source" in parameters:
        cameras, sources = as_list(parameters.get("camera", [])), as_list(parameters.get("source", []))
        infos = as_list(parameters.get("camera_info_key", [None] * len(cameras)))
        frames = as_list(parameters.get("frames", True))
        frames = frames * len(cameras) if len(frames) == 1 else frames  # one bool for every camera, or one each
        if not len(cameras) == len(sources) == len(infos) == len(frames):
            raise ValueError(
                f"{len(cameras)} camera, {len(sources)} source, {len(infos)} camera_info_key, {len(frames)} frames "
                "parameters"
            )
        overrides["cameras"] = [
            {"camera": c, "source": s, "camera_info_key": i or None, "frames": bool(f)}  # '' key: none for it
            for c, s, i, f in zip(cameras, sources, infos, frames, strict=True)
        ]
    safe = {field: parameters[name] for name, field in SAFE_MASK_PARAMETERS.items() if name in parameters}
    if safe:
        overrides["safe_mask"] = safe
    measured = {field: parameters[name] for name, field in OUTCOME_PARAMETERS.items() if name in parameters}
    if parameters.get("outcomes") or measured:  # outcomes:=true, or any of their topics: measured on the robot
        overrides["outcomes"] = measured
    if "odometry_key" in parameters or "odometry_topic" in parameters:  # a topic alone: the safe mask's centre
        odometry = {"key": parameters.get("odometry_key"), "topic": parameters.get("odometry_topic")}
        overrides["odometry"] = {name: value for name, value in odometry.items() if value is not None}
    return overrides
