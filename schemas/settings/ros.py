"""ROS 2 settings: camera inputs, the node in the ROS graph, its output topics."""

from __future__ import annotations

import re
from typing import Literal

from gcdtrav.schemas.settings.base import KEY_CHUNK
from gcdtrav.schemas.strict import StrictModel
from pydantic import Field, field_validator, model_validator

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")


class RosInput(StrictModel):
    """ROS 2 camera topics reaching Zenoh through rmw_zenoh or zenoh-bridge-ros2dds (CDR payloads)."""

    key: str = Field(
        description="Key expression, e.g. '0/**/sensor_msgs::msg::dds_::Image_/*' (rmw_zenoh) "
        "or 'camera/front/image_raw' (bridge: the topic name)."
    )
    layout: Literal["rmw_zenoh", "bridge"] = "rmw_zenoh"
    message_type: Literal["auto", "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"] = Field(
        default="auto", description="auto: read from the rmw_zenoh key; bridge keys carry no type, so set it."
    )
    zenoh_namespace: str = Field(
        default="",
        description="The robot's zenoh session 'namespace': its keys (and graph tokens) start with it, e.g. "
        "'robot1' for robot1/0/camera/...; key must start with it too. Outputs are published under it.",
    )

    @model_validator(mode="after")
    def _bridge_needs_a_type(self) -> RosInput:
        if self.layout == "bridge" and self.message_type == "auto":
            raise ValueError(
                f"ros input '{self.key}': bridge keys carry no type; set message_type to one of "
                f"{', '.join(IMAGE_TYPES)}"
            )
        namespace = self.zenoh_namespace
        if namespace and not all(KEY_CHUNK.match(chunk) for chunk in namespace.split("/")):
            raise ValueError(f"ros input '{self.key}': zenoh_namespace '{namespace}' must be a literal key")
        if namespace and not self.key.startswith(namespace + "/"):
            raise ValueError(f"ros input '{self.key}': the key must start with its zenoh_namespace '{namespace}/'")
        return self


_ROS_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class RosNode(StrictModel):
    """The service's node in the ROS 2 graph of rmw_zenoh robots (``ros2 node list`` shows /<namespace>/<name>)."""

    name: str = Field(default="gcdtrav", description="ROS node name.")
    namespace: str = Field(default="/", description="ROS namespace of the node, e.g. / or /robot1.")

    @field_validator("name")
    @classmethod
    def _node_name(cls, value: str) -> str:
        if not _ROS_NAME.match(value):
            raise ValueError(f"'{value}' is not a ROS node name (letters, digits and _, not starting with a digit)")
        return value

    @field_validator("namespace")
    @classmethod
    def _node_namespace(cls, value: str) -> str:
        chunks = value.strip("/").split("/") if value != "/" else []
        if not value.startswith("/") or not all(_ROS_NAME.match(chunk) for chunk in chunks):
            raise ValueError(f"'{value}' is not a ROS namespace: '/' or '/name[/name...]'")
        return value.rstrip("/") or "/"


def _topic_template(value: str) -> str:
    name = value.replace("{topic}", "t").strip("/")
    if not name or not all(_ROS_NAME.match(chunk) or chunk == "t" for chunk in name.split("/")):
        raise ValueError(f"'{value}' is not a ROS topic name ({{topic}} stands for the camera's topic)")
    return value


def output_topic(template: str, camera_topic: str) -> str:
    """An output topic from its template: '{topic}/gcdtrav/traversability' -> '/cam/gcdtrav/traversability'. The
    service's ROS outputs and the ROS relay's (client/relay/ros2_node.py) are named by this one rule."""
    return "/" + template.replace("{topic}", camera_topic.strip("/")).strip("/")


class RosOutput(StrictModel):
    """Maps as ROS 2 topics; ``{topic}`` in a topic stands for the camera's topic (without the leading slash)."""

    enabled: bool = False
    preview: Literal["compressed", "image", "none"] = Field(
        default="compressed",
        description="preview as CompressedImage (jpeg) on <preview_topic>/compressed, as image_transport "
        "names it, as Image (rgb8) on <preview_topic>, or not at all",
    )
    traversability_topic: str = "{topic}/gcdtrav/traversability"
    uncertainty_topic: str = "{topic}/gcdtrav/uncertainty"
    preview_topic: str = "{topic}/gcdtrav/preview"
    occupancy_topic: str = Field(
        default="{topic}/gcdtrav/grid/occupancy",
        description="nav_msgs/OccupancyGrid of the camera's grid, cost 100 (1 - T) (grids with occupancy_grid).",
    )
    grid_uncertainty_topic: str = "{topic}/gcdtrav/grid/uncertainty"
    gridmap_topic: str = Field(
        default="{topic}/gcdtrav/grid/gridmap",
        description="grid_map_msgs/GridMap of the camera's grid, every layer (grids with grid_map).",
    )
    costmap_topic: str = Field(
        default="{topic}/gcdtrav/grid/costmap",
        description="nav_msgs/OccupancyGrid graded for Nav2's static layer (grids with costmap; docs/grid.md).",
    )
    nav2_costmap_topic: str = Field(
        default="{topic}/gcdtrav/grid/nav2_costmap",
        description="nav2_msgs/Costmap of the same costs, stamped with the newest fused frame's capture: Nav2's "
        "collision monitor's costmap source, which stops the robot when it is older than its source_timeout.",
    )
    speed_mask_topic: str = Field(
        default="{topic}/gcdtrav/grid/speed_mask",
        description="nav_msgs/OccupancyGrid speed filter mask, percent of maximum speed, 0 = no limit (grids with "
        "speed; docs/grid.md).",
    )
    speed_filter_info_topic: str = Field(
        default="{topic}/gcdtrav/grid/speed_filter_info",
        description="nav2_msgs/CostmapFilterInfo of the speed mask (type 1, percent): a SpeedFilter's "
        "filter_info_topic.",
    )
    speed_limit_topic: str = Field(
        default="{topic}/gcdtrav/grid/speed_limit",
        description="nav2_msgs/SpeedLimit at the robot's pose, for a controller without a SpeedFilter (e.g. "
        "'speed_limit', controller_server's own topic).",
    )

    _templates = field_validator(
        "traversability_topic",
        "uncertainty_topic",
        "preview_topic",
        "occupancy_topic",
        "grid_uncertainty_topic",
        "gridmap_topic",
        "costmap_topic",
        "nav2_costmap_topic",
        "speed_mask_topic",
        "speed_filter_info_topic",
        "speed_limit_topic",
    )(_topic_template)

    def topic_templates(self) -> list[str]:
        """Every output topic; the compressed preview is a subtopic of the preview's."""
        return [
            self.traversability_topic,
            self.uncertainty_topic,
            self.preview_topic,
            self.preview_topic + "/compressed",
            self.occupancy_topic,
            self.grid_uncertainty_topic,
            self.gridmap_topic,
            self.costmap_topic,
            self.nav2_costmap_topic,
            self.speed_mask_topic,
            self.speed_filter_info_topic,
            self.speed_limit_topic,
        ]
