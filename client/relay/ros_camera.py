"""ROS 2 camera topics for the relay on a robot: the key expressions their messages come on and the types those
keys name (rmw_zenoh or zenoh-bridge-ros2dds). The messages are read by schemas/ros_image.py (numpy only),
the reader the service uses too.
"""

from __future__ import annotations

from gcdtrav.schemas.ros_image import ros_type_name


def ros_camera_key(topic: str, layout: str, domain: int = 0, namespace: str = "") -> str:
    """The key expression of a camera topic's messages: rmw_zenoh '<domain>/<topic>/<type>/<hash>' (any type
    and hash) or the bridge's topic name."""
    name = topic.strip("/")
    key = name if layout == "bridge" else f"{domain}/{name}/*/*"
    return f"{namespace}/{key}" if namespace else key


def ros_type_of_key(key: str) -> str | None:
    """The message type an rmw_zenoh key names (its second-to-last chunk)."""
    chunks = key.split("/")
    return ros_type_name(chunks[-2]) if len(chunks) >= 3 else None
