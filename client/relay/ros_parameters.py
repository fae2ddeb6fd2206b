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
)


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
        if not len(cameras) == len(sources) == len(infos):
            raise ValueError(f"{len(cameras)} camera, {len(sources)} source, {len(infos)} camera_info_key parameters")
        overrides["cameras"] = [
            {"camera": c, "source": s, "camera_info_key": i or None}  # '' in a list of keys: none for this camera
            for c, s, i in zip(cameras, sources, infos, strict=True)
        ]
    if "odometry_key" in parameters:
        overrides["odometry"] = {"key": parameters["odometry_key"]} | (
            {"topic": parameters["odometry_topic"]} if "odometry_topic" in parameters else {}
        )
    return overrides
