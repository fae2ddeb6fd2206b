"""Launch `gcdtrav relay --ros` on a robot with a ROS 2 workspace (docs/ros2.md):

    source /opt/ros/jazzy/setup.bash          # the robot's own rclpy, on its own RMW (Fast DDS, Cyclone, ...)
    python -m pip install dist/gcdtrav-*.whl   # the base install's wheel (docs/ros2.md): no torch
    ros2 launch examples/ros2/relay.launch.py offboard:=tcp/192.168.1.20:7447

The relay is a console script, not a ROS package: launch_ros runs the executable found on PATH (no
``package``) and adds the node name, namespace, parameters and remappings as ``--ros-args``.

Outputs are named after each camera's resolved topic (after remapping): the front camera's T, U, costmap and
speed filter mask under /front_camera/color/image_raw/gcdtrav/. The robot's software parks a camera with
std_msgs/Bool on <camera topic>/gcdtrav/parked (reliable, transient local).

Speed filter: where the relay's Python has nav2_msgs (the robot's ROS sourced, Nav2 installed) it publishes the
mask's CostmapFilterInfo itself. Where it has not (the relay on the PyPI ROS wheels), ``filter_info_server:=true``
runs Nav2's costmap_filter_info_server with the same info (type 1: percent, base 0, multiplier 1) and a lifecycle
manager that activates it; never both on one topic.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

FRONT_CAMERA = "/front_camera/color/image_raw"  # the front camera's topic after the remapping below
SPEED_MASK_TOPIC = f"{FRONT_CAMERA}/gcdtrav/grid/speed_mask"
SPEED_FILTER_INFO_TOPIC = f"{FRONT_CAMERA}/gcdtrav/grid/speed_filter_info"  # a SpeedFilter's filter_info_topic


def generate_launch_description() -> LaunchDescription:
    offboard = LaunchConfiguration("offboard")
    info_server = IfCondition(LaunchConfiguration("filter_info_server"))
    return LaunchDescription(
        [
            DeclareLaunchArgument("offboard", default_value="tcp/127.0.0.1:7447", description="the service's zenoh"),
            DeclareLaunchArgument("use_sim_time", default_value="false"),
            DeclareLaunchArgument(
                "filter_info_server", default_value="false", description="the relay cannot import nav2_msgs"
            ),
            Node(
                executable="gcdtrav",
                arguments=["relay", "--ros", "-e", offboard],
                name="gcdtrav_relay",
                namespace="r1",  # relative topics below resolve under /r1
                output="screen",
                parameters=[
                    {
                        "camera": ["front/image_raw", "rear/image_raw/compressed"],
                        "source": ["r1/front", "r1/rear"],
                        # the service's grid takes the front camera's intrinsics from this key ('': none)
                        "camera_info_key": ["robot/r1/front/camera_info", ""],
                        "odometry_topic": "odom",
                        "odometry_key": "robot/r1/pose",
                        "use_sim_time": LaunchConfiguration("use_sim_time"),
                    }
                ],
                # the driver publishes elsewhere: remap instead of editing the parameters
                remappings=[("front/image_raw", FRONT_CAMERA)],
            ),
            Node(
                package="nav2_map_server",
                executable="costmap_filter_info_server",
                name="gcdtrav_speed_filter_info",
                condition=info_server,
                parameters=[
                    {
                        "type": 1,  # speed limit in percent of the maximum speed: a mask value v is v percent
                        "filter_info_topic": SPEED_FILTER_INFO_TOPIC,
                        "mask_topic": SPEED_MASK_TOPIC,
                        "base": 0.0,
                        "multiplier": 1.0,
                    }
                ],
            ),
            Node(
                package="nav2_lifecycle_manager",
                executable="lifecycle_manager",
                name="gcdtrav_speed_filter_lifecycle",
                condition=info_server,
                parameters=[{"autostart": True, "node_names": ["gcdtrav_speed_filter_info"]}],
            ),
        ]
    )
