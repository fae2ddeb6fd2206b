"""schemas/access.py, the identity list: a robot's ROS rights are its namespace's keys, so no robot may be named
like a topic every robot shares."""

from __future__ import annotations

import pytest
from gcdtrav.schemas.access import SHARED_TOPICS, FleetIdentities, robot_rules


@pytest.mark.parametrize("name", ["tf", "odom", "cmd_vel"])
def test_a_robot_named_like_a_shared_topic_is_refused(name: str) -> None:
    """Before, robot 'tf' was given put rights on 0/tf/**: every robot's /tf."""
    with pytest.raises(ValueError, match=f"robot name '{name}' is a ROS topic robots share"):
        FleetIdentities(robots=["r1", name])


def test_other_names_and_other_roles_are_taken() -> None:
    identities = FleetIdentities(robots=["r7", "tf2", "odom-bot"], planners=["tf"], ros_domains=[0, 5])
    puts = next(rule for rule in robot_rules("r7", identities) if rule["id"] == "robot-r7-puts")
    assert "0/r7/**" in puts["key_exprs"] and "5/r7/**" in puts["key_exprs"]
    assert not any(key.startswith(("0/tf", "5/tf")) for key in puts["key_exprs"])
    assert "tf_static" in SHARED_TOPICS and "r7" not in SHARED_TOPICS
