"""The ROS 2 relay on a robot with nav2_msgs (one that runs Nav2). No nav2_msgs wheel exists, so its three types
stand in as other real ROS types: the relay publishes them as CDR bytes, which the topics carry as they are.
Before: the SpeedLimit's forwarder asked for a key the service never uses and the relay stopped at its start
(ValueError: unknown output kind 'speed_limit'); a safe mask put before any live mask came without the
CostmapFilterInfo that makes Nav2's SpeedFilter subscribe to the mask at all."""

from __future__ import annotations

import random
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest
from real_components import require_rclpy
from zenoh_helpers import wait_until

require_rclpy()

from gcdtrav.client.relay import ros2_node  # noqa: E402
from gcdtrav.client.relay.mask_guard import SafeMask  # noqa: E402
from gcdtrav.schemas.keys import Keys  # noqa: E402
from gcdtrav.schemas.ros_nav import costmap_filter_info_cdr, occupancy_grid_geometry  # noqa: E402

from tools.ros2_robot import RosRobot, ros_environment  # noqa: E402

DOMAIN = random.randint(100, 200)
SOURCE, TOPIC = "r1/front", "/r1/front/image_raw"


@pytest.fixture(scope="module")
def robot() -> Iterator[RosRobot]:
    with ros_environment(DOMAIN):
        robot = RosRobot("relay_with_nav2")
        try:
            yield robot
        finally:
            robot.close()


@pytest.fixture
def with_nav2(monkeypatch: pytest.MonkeyPatch) -> None:
    from nav_msgs.msg import OccupancyGrid
    from std_msgs.msg import Header, String

    # types of unbounded size, as nav2's are (a bounded type's publisher refuses a longer message)
    monkeypatch.setattr(ros2_node, "nav2_messages", lambda: (String, Header, OccupancyGrid))


@dataclass
class CameraStub:
    source: str = SOURCE

    def ros_stamp(self, stamp: float) -> tuple[int, int]:
        return int(stamp), 0


@dataclass
class RelayStub:
    keys: Keys


def test_the_speed_limit_is_forwarded_from_where_the_service_puts_it(robot: RosRobot, with_nav2: Any) -> None:
    topics = ros2_node.SpeedTopics(robot.node, TOPIC, CameraStub())  # type: ignore[arg-type]
    outputs = topics.outputs(RelayStub(Keys()), SOURCE)  # type: ignore[arg-type]
    assert {output.kind: output.key for output in outputs} == {
        "speed_mask": f"gcdtrav/out/{SOURCE}/grid/speed_mask",
        "speed_limit": f"gcdtrav/out/{SOURCE}/grid/speed_limit",  # service/runtime/outputs.py's key
    }


def test_a_safe_mask_before_any_live_one_comes_with_its_filter_info(robot: RosRobot, with_nav2: Any) -> None:
    from nav_msgs.msg import OccupancyGrid
    from std_msgs.msg import String

    topics = ros2_node.SpeedTopics(robot.node, TOPIC, CameraStub())  # type: ignore[arg-type]
    info_topic = ros2_node.output_topic(ros2_node.NAMES.speed_filter_info_topic, TOPIC)
    _, infos = robot.subscribe(String, info_topic, ros2_node.LATCHED_QOS, raw=True)
    _, masks = robot.subscribe(OccupancyGrid, topics.mask_topic, ros2_node.LATCHED_QOS, raw=True)
    mask = SafeMask(SOURCE, "odom", 1.0, 4, (-2.0, -2.0), 30, "the service went quiet")
    topics.publish_safe(mask, (int(time.time()), 0))
    assert wait_until(lambda: len(infos) == 1 and len(masks) == 1, 10)
    assert infos.last == costmap_filter_info_cdr("odom", topics.mask_topic)
    assert occupancy_grid_geometry(masks.last).frame_id == "odom"
    topics.publish_safe(mask, (int(time.time()), 0))  # the same frame: no new info (each makes SpeedFilter resubscribe)
    assert wait_until(lambda: len(masks) == 2, 10)
    time.sleep(0.2)
    assert len(infos) == 1


def test_a_safe_mask_comes_with_the_floor_as_a_speed_limit(robot: RosRobot, with_nav2: Any) -> None:
    """For a controller that takes the SpeedLimit directly (docs/grid.md): before, it kept the last live limit,
    0 (no limit) on clear ground, as long as the link was dead."""
    pytest.importorskip("rosbags")
    from gcdtrav.service.ros.cdr import speed_limit_cdr
    from std_msgs.msg import Header

    topics = ros2_node.SpeedTopics(robot.node, "/r2/front/image_raw", CameraStub())  # type: ignore[arg-type]
    limit_topic = ros2_node.output_topic(ros2_node.NAMES.speed_limit_topic, "/r2/front/image_raw")
    _, limits = robot.subscribe(Header, limit_topic, 10, raw=True)
    assert wait_until(lambda: topics.limit.get_subscription_count() == 1, 10)  # volatile: subscribed first
    mask = SafeMask(SOURCE, "odom", 1.0, 4, (-2.0, -2.0), 30, "the service went quiet")
    topics.publish_safe(mask, (12, 345))
    assert wait_until(lambda: len(limits) == 1, 10)
    assert limits.last == speed_limit_cdr(12.000000345, "odom", 30.0)  # the service's own SpeedLimit, byte for byte
