"""nav2_msgs' speed filter messages in gcdtrav's type store: their RIHS01 hashes as ROS 2's own generator
(rosidl_adapter's .msg -> .idl, then rosidl_generator_type_description) computes them from the .msg files of
Nav2's Kilted release 1.4.2, shipped verbatim in service/ros/nav2_msgs.py; and the messages round-trip."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest
from gcdtrav.service.bus.ros_graph import GRID_QOS, Entity, NodeName, TopicInfo
from gcdtrav.service.ros import cdr, nav2_msgs

from tests.real_components import missing

# Computed by rosidl_generator_type_description 4.9.5 (Kilted) from navigation2 tag 1.4.2's nav2_msgs/msg files
# (identical on the jazzy branch); the test recomputes them where the generator is installed.
KILTED_HASHES = {
    nav2_msgs.COSTMAP_FILTER_INFO: "RIHS01_61ce391bf7690f76a331c01c9d5ce8ca71e6c99273b9fb75e48380f05c6dfdc8",
    nav2_msgs.SPEED_LIMIT: "RIHS01_83d8e4e842559f4d9a988b19d31b162216ec738536389f98438d1a166f91845a",
    # navigation2 main's Costmap.msg and CostmapMetaData.msg (the collision monitor's costmap source), same generator
    nav2_msgs.COSTMAP_META_DATA: "RIHS01_1a41ec8428d50c3b4cd3f9055e1adb0eaec72fb39ae11686b59218f6e0884cbd",
    nav2_msgs.COSTMAP: "RIHS01_d51bf7aecafdbb3f8f98215de648abe6d53f8db69156d6e143125d2ad2bf0027",
}


def _share_of(package: str) -> Path:
    """Where a ROS 2 wheel installed a package's share directory (its type description JSONs): <prefix>/share,
    beside <prefix>/lib/python3.X/site-packages."""
    spec = importlib.util.find_spec(package)
    assert spec is not None and spec.origin is not None
    return Path(spec.origin).parents[4] / "share" / package


def official_hashes(tmp_path: Path) -> dict[str, str]:
    """RIHS01 of each shipped nav2_msgs .msg, by ROS 2's generator, as colcon builds nav2_msgs."""
    if (
        importlib.util.find_spec("rosidl_generator_type_description") is None
        or importlib.util.find_spec("std_msgs") is None
    ):
        missing("rclpy", "pip install -r tests/requirements-ros2.txt")
    from rosidl_adapter.msg import convert_msg_to_idl
    from rosidl_generator_type_description import generate_type_hash

    package, idl = tmp_path / "nav2_msgs", tmp_path / "idl"
    (package / "msg").mkdir(parents=True)
    tuples = []
    for name, text in nav2_msgs.MESSAGES.items():
        msg = package / "msg" / f"{name.split('/')[-1]}.msg"
        msg.write_text(text)
        written = convert_msg_to_idl(package, "nav2_msgs", msg.relative_to(package), idl / "msg")
        tuples.append(f"{idl}:{written.relative_to(idl)}")
    arguments = tmp_path / "arguments.json"
    includes = [f"{name}:{_share_of(name)}" for name in ("std_msgs", "builtin_interfaces", "geometry_msgs")]
    arguments.write_text(
        json.dumps(
            {"package_name": "nav2_msgs", "output_dir": str(tmp_path / "out"), "idl_tuples": tuples,
             "include_paths": includes}
        )
    )  # fmt: skip
    found = {}
    for path in generate_type_hash(str(arguments)):
        top = json.loads(path.read_text())["type_hashes"][0]
        found[top["type_name"]] = top["hash_string"]
    return found


def test_type_store_hashes_are_ros2_generators(tmp_path: Path) -> None:
    official = official_hashes(tmp_path)
    assert official == KILTED_HASHES
    for name, expected in official.items():
        assert cdr.type_hash(name) == expected


def test_type_store_hashes_match_the_release() -> None:
    """Without the generator too: rosbags' hash of the shipped text is the release's."""
    for name, expected in KILTED_HASHES.items():
        assert cdr.type_hash(name) == expected


def test_filter_info_and_speed_limit_round_trip() -> None:
    store = cdr.typestore()
    info = store.deserialize_cdr(
        cdr.costmap_filter_info_cdr("odom", "/cam/gcdtrav/grid/speed_mask"), nav2_msgs.COSTMAP_FILTER_INFO
    )
    assert (info.type, info.base, info.multiplier) == (1, 0.0, 1.0)
    assert info.filter_mask_topic == "/cam/gcdtrav/grid/speed_mask" and info.header.frame_id == "odom"
    limit = store.deserialize_cdr(cdr.speed_limit_cdr(12.25, "odom", 30.0), nav2_msgs.SPEED_LIMIT)
    assert limit.percentage and limit.speed_limit == 30.0
    assert (limit.header.stamp.sec, limit.header.stamp.nanosec) == (12, 250_000_000)


@pytest.mark.parametrize("msgtype", list(KILTED_HASHES))
def test_graph_token_names_the_type_and_its_hash(msgtype: str) -> None:
    topic = cdr.RosTopic("/cam/gcdtrav/grid/speed_filter_info", msgtype, "rmw_zenoh")
    entity = Entity("z", 1, 2, "MP", NodeName(0, "/", "gcdtrav"), TopicInfo.of(topic, GRID_QOS))
    name = msgtype.split("/")[-1]
    assert f"/nav2_msgs::msg::dds_::{name}_/{KILTED_HASHES[msgtype]}/" in entity.token
    assert cdr.topic_key(topic).endswith(f"nav2_msgs::msg::dds_::{name}_/{KILTED_HASHES[msgtype]}")


def test_the_nav2_costmap_holds_the_costs_nav2s_static_layer_reads_from_the_occupancy_grid() -> None:
    """-1 unknown -> NO_INFORMATION 255, 100 -> LETHAL 254, a grade v -> v / 100 x 254 truncated (static_layer.cpp
    interpretValue, trinary_costmap false): the collision monitor sees what the costmap layer sees."""
    import numpy as np
    from gcdtrav.schemas.messages import GridHeader

    values = np.array([[-1, 0, 1, 50], [97, 98, 99, 100]], np.int8)
    assert cdr.nav2_cost_values(values).tolist() == [[255, 0, 2, 127], [246, 248, 251, 254]]
    header = GridHeader(
        source="r1/front",
        seq=3,
        stamp=12.5,
        frame_id="odom",
        origin=(-1.0, 2.0),
        resolution=0.25,
        cells=2,
        anchor_set_version="v",
        resets=0,
        known_cells=3,
        instance="box-1",
    )
    square = np.array([[-1, 100], [1, 98]], np.int8)
    costmap = cdr.typestore().deserialize_cdr(cdr.nav2_costmap_cdr(header, square), nav2_msgs.COSTMAP)
    assert (costmap.header.stamp.sec, costmap.header.stamp.nanosec, costmap.header.frame_id) == (
        12,
        500_000_000,
        "odom",
    )
    meta = costmap.metadata
    assert (meta.size_x, meta.size_y, meta.resolution, meta.layer) == (2, 2, 0.25, "gcdtrav")
    assert (meta.origin.position.x, meta.origin.position.y, meta.update_time.sec) == (-1.0, 2.0, 12)
    assert costmap.data.tolist() == [255, 254, 2, 248]
