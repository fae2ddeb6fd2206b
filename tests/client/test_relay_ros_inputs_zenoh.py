"""The zenoh relay of an rmw_zenoh robot reads its outcome inputs as ROS topics (docs/calibration.md's relay.yaml):
a nav_msgs/Path on `/plan` arrives at the service as a PlannedPath. Before, `planned_path: /plan` (the example in
the docs) stopped the relay at its start with a KeyError."""

from __future__ import annotations

import pytest
import zenoh
from gcdtrav.client.relay.relay import Relay
from gcdtrav.client.session.zenoh_args import zenoh_config
from gcdtrav.schemas.experience import PlannedPath
from gcdtrav.schemas.relay import RelaySettings
from zenoh_helpers import connecting_config, free_port, subscribed_elsewhere, wait_until

from tests.schemas.test_ros_nav import rosbags_path

SOURCE = "r1/front"
PATH_KEY = "0/plan/nav_msgs::msg::dds_::Path_/RIHS01_dd8e6f3f0bf1fa24b7bc3a0b8c7bd7f6c6d6d6e6f3f0bf1fa24b7bc3a0b8c7bd"


def test_a_path_on_a_ros_topic_reaches_the_service_and_a_bad_one_is_counted() -> None:
    pytest.importorskip("rosbags")
    service_port, robot_port = free_port(), free_port()
    service = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{service_port}"], multicast_scouting=False))
    bus = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{robot_port}"], multicast_scouting=False))
    link = zenoh.open(connecting_config(service_port, mode="client"))
    local = zenoh.open(connecting_config(robot_port, mode="client"))
    received: list[PlannedPath] = []

    def on_path(sample: zenoh.Sample) -> None:
        received.append(PlannedPath.unpack(sample.payload.to_bytes()))

    subscriber = service.declare_subscriber(f"gcdtrav/in/{SOURCE}/planned_path", on_path)
    settings = RelaySettings.model_validate(
        {
            "cameras": [{"camera": "robot/unused", "source": SOURCE, "frames": False}],
            "safe_mask": {"enabled": False},
            "outcomes": {"cmd_vel": None, "planned_path": "/plan", "batch_period_s": 0.1},
        }
    )
    relay = Relay(settings, link, local).start()  # raised KeyError: 'planned_path'
    try:
        assert subscribed_elsewhere(bus, PATH_KEY, 30)
        outcomes = relay.outcomes
        assert outcomes is not None
        bus.put(PATH_KEY, b"\x00\x01\x00\x00 not a path")
        assert wait_until(lambda: outcomes.rejected == 1, 10)
        bus.put(PATH_KEY, rosbags_path("odom", [(0.0, 0.0), (1.0, 0.0), (2.0, 0.5)], "odom"))
        assert wait_until(lambda: len(received) >= 1, 10)
        assert received[0].frame_id == "odom" and received[0].points == [(0.0, 0.0), (1.0, 0.0), (2.0, 0.5)]
        assert outcomes.rejected == 1
    finally:
        relay.close()
        subscriber.undeclare()
        for session in (local, link, bus, service):
            session.close()
